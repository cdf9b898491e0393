//! Stillstand detection, sans-I/O: fed (time, length) samples one by one, it says whether
//! the readings have stayed within a tolerance band for a whole window. Used live and on replay.

use std::collections::VecDeque;

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Stillstand {
    /// Not enough history yet, or the readings still move.
    Moving,
    /// Settled: every sample since `since_s` lies within the tolerance band.
    Settled { since_s: f64 },
}

/// Sliding-window peak-to-peak test with monotonic queues: O(1) amortised per sample.
#[derive(Debug, Clone)]
pub struct StillstandDetector {
    window_s: f64,
    tolerance_m: f64,
    samples: VecDeque<(f64, f64)>,
    maxima: VecDeque<(f64, f64)>,
    minima: VecDeque<(f64, f64)>,
    /// Start of the current settled stretch, kept while the band holds.
    settled_since_s: Option<f64>,
}

impl StillstandDetector {
    pub fn new(window_s: f64, tolerance_m: f64) -> Self {
        Self {
            window_s,
            tolerance_m,
            samples: VecDeque::new(),
            maxima: VecDeque::new(),
            minima: VecDeque::new(),
            settled_since_s: None,
        }
    }

    pub fn reset(&mut self) {
        self.samples.clear();
        self.maxima.clear();
        self.minima.clear();
        self.settled_since_s = None;
    }

    /// Feed one sample (times must not decrease); returns the state after it.
    pub fn push(&mut self, t_s: f64, length_m: f64) -> Stillstand {
        self.samples.push_back((t_s, length_m));
        while self.maxima.back().is_some_and(|&(_, v)| v <= length_m) {
            self.maxima.pop_back();
        }
        self.maxima.push_back((t_s, length_m));
        while self.minima.back().is_some_and(|&(_, v)| v >= length_m) {
            self.minima.pop_back();
        }
        self.minima.push_back((t_s, length_m));

        // Keep exactly the samples of the last window_s.
        while self
            .samples
            .front()
            .is_some_and(|&(t, _)| t < t_s - self.window_s)
        {
            let (t_old, _) = self.samples.pop_front().unwrap_or_default();
            if self.maxima.front().is_some_and(|&(t, _)| t <= t_old) {
                self.maxima.pop_front();
            }
            if self.minima.front().is_some_and(|&(t, _)| t <= t_old) {
                self.minima.pop_front();
            }
        }
        let span_s = match (self.samples.front(), self.samples.back()) {
            (Some(first), Some(last)) => last.0 - first.0,
            _ => 0.0,
        };
        let peak_to_peak = match (self.maxima.front(), self.minima.front()) {
            (Some(max), Some(min)) => max.1 - min.1,
            _ => f64::INFINITY,
        };
        // A full window is one that spans window_s to within one sample period.
        let full = span_s >= self.window_s * (1.0 - 1e-9) - self.sample_period_s();
        if full && peak_to_peak <= self.tolerance_m {
            let start = self.samples.front().map_or(t_s, |s| s.0);
            let since = *self.settled_since_s.get_or_insert(start);
            Stillstand::Settled { since_s: since }
        } else {
            self.settled_since_s = None;
            Stillstand::Moving
        }
    }

    fn sample_period_s(&self) -> f64 {
        let n = self.samples.len();
        if n < 2 {
            return 0.0;
        }
        let span = self.samples[n - 1].0 - self.samples[0].0;
        span / (n - 1) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settles_after_motion_stops() {
        let mut d = StillstandDetector::new(0.5, 1e-6);
        let mut settled_at = None;
        for k in 0..300 {
            let t = k as f64 * 0.01;
            // Moves at 10 mm/s until t = 1 s, then holds still with 0.1 um wiggle.
            let x = if t < 1.0 {
                0.01 * t
            } else {
                0.01 + 1e-7 * (k % 3) as f64
            };
            if let Stillstand::Settled { since_s } = d.push(t, x) {
                settled_at.get_or_insert((t, since_s));
            }
        }
        let (t, since) = settled_at.expect("never settled");
        assert!((t - 1.5).abs() < 0.02, "settled reported at {t}");
        assert!((since - 1.0).abs() < 0.02, "settled since {since}");
    }

    #[test]
    fn never_settles_while_moving() {
        let mut d = StillstandDetector::new(0.5, 1e-6);
        for k in 0..1000 {
            let t = k as f64 * 0.01;
            assert_eq!(d.push(t, 1e-5 * t), Stillstand::Moving);
        }
    }

    #[test]
    fn a_jump_breaks_the_settled_stretch() {
        let mut d = StillstandDetector::new(0.2, 1e-6);
        for k in 0..50 {
            d.push(k as f64 * 0.01, 0.0);
        }
        assert!(matches!(d.push(0.5, 0.0), Stillstand::Settled { .. }));
        assert_eq!(d.push(0.51, 5e-6), Stillstand::Moving);
    }
}
