//! Sample times of the fixed-rate distance stream. The frames carry no device time, so each
//! frame is placed on the device's tick grid by its count, the grid anchored on the recent
//! frames that arrived with the least delay. Sans-I/O: fed (seq, reception time), returns times.

use std::collections::VecDeque;

/// How much of the stream the anchor looks back over, seconds. Long enough to hold frames
/// that came through without delay on a loaded host; short enough that a device clock off by
/// 100 ppm moves the grid by at most 0.2 ms within it, and that a frame lost whole (which
/// leaves no trace in the count) shifts the times by one period for at most this long.
pub const ANCHOR_WINDOW_S: f64 = 2.0;

/// A reception gap at least this long starts a new anchor: frames the device did not send
/// (a silence, a stream switched off and on) leave no trace in the count either.
pub const RESTART_GAP_S: f64 = 0.25;

/// Times of a stream of frames counted by `seq` at a fixed rate: frame `seq` received at
/// `recv_s` is given `min over the window of (recv - seq × period) + seq × period`, held
/// non-decreasing. So a time is never later than its frame's reception, and a burst of
/// frames read at once is spread back over the ticks they were measured at.
#[derive(Debug, Clone)]
pub struct StreamClock {
    period_s: f64,
    window_frames: u64,
    restart_gap_s: f64,
    anchor: Option<Anchor>,
    last_t_s: f64,
}

/// The grid since the last restart.
#[derive(Debug, Clone)]
struct Anchor {
    /// Ticks count from this frame, so the offsets keep their precision.
    first_seq: u64,
    last_seq: u64,
    last_recv_s: f64,
    /// (seq, recv − ticks × period) of the window's frames whose offset no later frame
    /// undercuts: offsets increase from front to back, the front is the window's minimum.
    envelope: VecDeque<(u64, f64)>,
}

impl StreamClock {
    /// A clock for `rate_hz` frames per second with the default windows; None unless the
    /// rate is finite and positive.
    pub fn new(rate_hz: f64) -> Option<Self> {
        Self::with_windows(rate_hz, ANCHOR_WINDOW_S, RESTART_GAP_S)
    }

    /// As `new`, with the anchor's look-back and the restarting gap in seconds.
    pub fn with_windows(rate_hz: f64, window_s: f64, restart_gap_s: f64) -> Option<Self> {
        let period_s = 1.0 / rate_hz;
        let valid = |x: f64| x.is_finite() && x > 0.0;
        if !(valid(rate_hz) && valid(period_s) && valid(window_s) && valid(restart_gap_s)) {
            return None;
        }
        // `as` saturates: a window longer than any stream holds every frame.
        let window_frames = ((window_s * rate_hz).ceil() as u64).max(1);
        Some(StreamClock {
            period_s,
            window_frames,
            restart_gap_s,
            anchor: None,
            last_t_s: f64::NEG_INFINITY,
        })
    }

    /// Forget the grid: the next frame starts a new one (the stream was switched on again).
    pub fn restart(&mut self) {
        self.anchor = None;
    }

    /// The time of frame `seq` received at `recv_s` (seconds; receptions must not go
    /// backwards). `seq` counts the device's ticks: a frame lost in between leaves a gap.
    pub fn stamp(&mut self, seq: u64, recv_s: f64) -> f64 {
        let continues = self
            .anchor
            .as_ref()
            .is_some_and(|a| seq > a.last_seq && recv_s - a.last_recv_s < self.restart_gap_s);
        if !continues {
            self.anchor = Some(Anchor {
                first_seq: seq,
                last_seq: seq,
                last_recv_s: recv_s,
                envelope: VecDeque::new(),
            });
        }
        let Some(anchor) = self.anchor.as_mut() else {
            return recv_s;
        };
        let grid_s = (seq - anchor.first_seq) as f64 * self.period_s;
        let offset_s = recv_s - grid_s;
        while anchor.envelope.back().is_some_and(|&(_, o)| o >= offset_s) {
            anchor.envelope.pop_back();
        }
        anchor.envelope.push_back((seq, offset_s));
        while anchor
            .envelope
            .front()
            .is_some_and(|&(s, _)| s + self.window_frames <= seq)
        {
            anchor.envelope.pop_front();
        }
        let floor_s = anchor.envelope.front().map_or(offset_s, |&(_, o)| o);
        anchor.last_seq = seq;
        anchor.last_recv_s = recv_s;
        // The floor is at most this frame's own offset, so only rounding could put the time
        // past the reception; the previous time is at most the previous reception.
        let t_s = (floor_s + grid_s).max(self.last_t_s).min(recv_s);
        self.last_t_s = t_s;
        t_s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    const RATE_HZ: f64 = 25.0;
    const PERIOD_S: f64 = 1.0 / RATE_HZ;
    /// The line's own transit time: every frame arrives at least this late.
    const TRANSIT_S: f64 = 0.0005;

    /// A frame as measured and as received.
    #[derive(Debug, Clone, Copy)]
    struct Frame {
        seq: u64,
        true_s: f64,
        recv_s: f64,
    }

    /// Frames measured at `true_s` (increasing), delivered in bursts: the reader wakes at
    /// random intervals of up to `max_sleep_s` and takes every frame that has arrived.
    fn bursty(
        frames: impl IntoIterator<Item = (u64, f64)>,
        max_sleep_s: f64,
        seed: u64,
    ) -> Vec<Frame> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut wake_s = 0.0;
        let mut out = Vec::new();
        for (seq, true_s) in frames {
            let arrived_s = true_s + TRANSIT_S;
            while wake_s < arrived_s {
                wake_s += rng.random_range(0.0..max_sleep_s);
            }
            out.push(Frame {
                seq,
                true_s,
                recv_s: wake_s,
            });
        }
        out
    }

    /// Stamp every frame; check that no time is later than its reception and that times
    /// never go backwards; return (frame, time).
    fn stamp_all(clock: &mut StreamClock, frames: &[Frame]) -> Vec<(Frame, f64)> {
        let mut last = f64::NEG_INFINITY;
        frames
            .iter()
            .map(|&f| {
                let t = clock.stamp(f.seq, f.recv_s);
                assert!(t <= f.recv_s, "{f:?} stamped {t}, after its reception");
                assert!(t >= last, "{f:?} stamped {t}, before the previous {last}");
                last = t;
                (f, t)
            })
            .collect()
    }

    /// Largest |time − (true time + transit)| over the frames from `skip` on.
    fn worst_error_s(stamped: &[(Frame, f64)], skip: usize) -> f64 {
        stamped[skip..]
            .iter()
            .map(|(f, t)| (t - f.true_s - TRANSIT_S).abs())
            .fold(0.0, f64::max)
    }

    /// The `q` quantile of |time − (true time + transit)| over the frames from `skip` on.
    fn error_quantile_s(stamped: &[(Frame, f64)], skip: usize, q: f64) -> f64 {
        let mut e: Vec<f64> = stamped[skip..]
            .iter()
            .map(|(f, t)| (t - f.true_s - TRANSIT_S).abs())
            .collect();
        e.sort_by(f64::total_cmp);
        e[((e.len() - 1) as f64 * q) as usize]
    }

    fn ticks(n: u64, period_s: f64, phase_s: f64) -> impl Iterator<Item = (u64, f64)> {
        (0..n).map(move |k| (k + 1, phase_s + k as f64 * period_s))
    }

    #[test]
    fn bursts_are_spread_back_onto_their_ticks() {
        // Reader asleep for up to 200 ms: bursts of up to 5 frames, 0-200 ms late.
        let frames = bursty(ticks(3000, PERIOD_S, 0.013), 0.2, 1);
        let late = frames
            .iter()
            .map(|f| f.recv_s - f.true_s)
            .fold(0.0, f64::max);
        assert!(late > 0.1, "the reception times are late by up to {late} s");
        let mut clock = StreamClock::new(RATE_HZ).unwrap();
        let stamped = stamp_all(&mut clock, &frames);
        // After the first window the anchor holds a frame read almost as it arrived.
        let skip = (ANCHOR_WINDOW_S * RATE_HZ) as usize;
        let worst = worst_error_s(&stamped, skip);
        assert!(worst < 0.02, "worst error {worst} s");
        // Half the frames within 3 ms, against half of them 30 ms late or more on reception.
        let median = error_quantile_s(&stamped, skip, 0.5);
        assert!(median < 0.003, "median error {median} s");
        let received: Vec<(Frame, f64)> = frames.iter().map(|&f| (f, f.recv_s)).collect();
        assert!(error_quantile_s(&received, skip, 0.5) > 0.03);
    }

    #[test]
    fn a_device_clock_off_by_100_ppm_does_not_accumulate() {
        for ppm in [-100.0, 100.0] {
            let period_s = PERIOD_S * (1.0 + ppm * 1e-6);
            // Ten minutes: a grid anchored once would be 60 ms off by the end.
            let frames = bursty(ticks(15_000, period_s, 0.0), 0.1, 2);
            let mut clock = StreamClock::new(RATE_HZ).unwrap();
            let stamped = stamp_all(&mut clock, &frames);
            let worst = worst_error_s(&stamped, 50);
            assert!(worst < 0.015, "{ppm} ppm: worst error {worst} s");
            let median = error_quantile_s(&stamped, 50, 0.5);
            assert!(median < 0.002, "{ppm} ppm: median error {median} s");
            if ppm > 0.0 {
                // A slow device's offsets grow: anchored on all of the stream, the times
                // fall behind.
                let mut forever = StreamClock::with_windows(RATE_HZ, 1e9, RESTART_GAP_S).unwrap();
                let drifted = worst_error_s(&stamp_all(&mut forever, &frames), 50);
                assert!(drifted > 0.03, "{ppm} ppm without a window: {drifted} s");
            }
        }
    }

    #[test]
    fn a_lost_frame_leaves_the_grid_in_place() {
        // Frames 40..43 fail their CRC: seq jumps, the ticks go on.
        let frames: Vec<Frame> = bursty(ticks(500, PERIOD_S, 0.0), 0.1, 3)
            .into_iter()
            .filter(|f| !(40..43).contains(&f.seq))
            .collect();
        let mut clock = StreamClock::new(RATE_HZ).unwrap();
        let stamped = stamp_all(&mut clock, &frames);
        let after_gap = stamped.iter().position(|(f, _)| f.seq == 43).unwrap();
        // Frames right behind the gap keep the anchor made before it.
        assert!(worst_error_s(&stamped[after_gap..after_gap + 10], 0) < 0.01);
        assert!(worst_error_s(&stamped, 50) < 0.01);
    }

    #[test]
    fn a_silence_or_restart_starts_a_new_grid() {
        // 20 s of stream, a second with nothing sent (seq goes on by one), then the device
        // ticks on a grid of another phase.
        let mut frames = bursty(ticks(500, PERIOD_S, 0.0), 0.05, 4);
        let resumed_s = frames.last().unwrap().true_s + 1.0 + 0.017;
        let base = frames.last().unwrap().seq;
        let later: Vec<(u64, f64)> = ticks(500, PERIOD_S, resumed_s)
            .map(|(k, t)| (base + k, t))
            .collect();
        frames.extend(bursty(later, 0.05, 5));
        let mut clock = StreamClock::new(RATE_HZ).unwrap();
        let stamped = stamp_all(&mut clock, &frames);
        // The new grid is found once its least-delayed frames have come; the old one would
        // put every later frame a second early.
        assert!(worst_error_s(&stamped[500 + 50..], 0) < 0.01);

        // A stream switched off and on without a long gap: restart() forgets the grid.
        let mut clock = StreamClock::new(RATE_HZ).unwrap();
        let first = stamp_all(&mut clock, &bursty(ticks(100, PERIOD_S, 0.0), 0.05, 6));
        let end_s = first.last().unwrap().0.recv_s;
        clock.restart();
        let again: Vec<(u64, f64)> = ticks(200, PERIOD_S, end_s + 0.1 + 0.021)
            .map(|(k, t)| (100 + k, t))
            .collect();
        let stamped = stamp_all(&mut clock, &bursty(again, 0.05, 7));
        assert!(worst_error_s(&stamped, 50) < 0.01);
    }

    #[test]
    fn a_stall_shorter_than_the_restart_gap_keeps_the_grid() {
        // The reader stalls for 200 ms once: the 5 frames behind it are placed on their ticks.
        let mut frames = bursty(ticks(400, PERIOD_S, 0.0), 0.01, 8);
        let stall_s = frames[300].true_s + 0.2;
        for f in &mut frames[300..306] {
            f.recv_s = f.recv_s.max(stall_s);
        }
        let mut clock = StreamClock::new(RATE_HZ).unwrap();
        let stamped = stamp_all(&mut clock, &frames);
        assert!(worst_error_s(&stamped[300..310], 0) < 0.005);
    }

    #[test]
    fn invalid_rates_are_refused() {
        for rate in [0.0, -25.0, f64::NAN, f64::INFINITY, 1e-320] {
            assert!(StreamClock::new(rate).is_none(), "{rate}");
        }
        assert!(StreamClock::with_windows(25.0, 0.0, 1.0).is_none());
        assert!(StreamClock::with_windows(25.0, 1.0, f64::NAN).is_none());
    }
}
