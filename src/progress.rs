//! What a person sees while geocal works: in a terminal one progress line updated in place
//! (phase, done/total, rate, time left, the station and point being measured); on a pipe or
//! in a log a line at each tenth of the work and at each new station, never one per point;
//! nothing with `--quiet`. Used by `geocal run`, `geocal client submit/follow`, `geocal
//! solve`, `geocal diagnose` and the daemon's log (`Cadence`).

use std::io::IsTerminal;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use crate::progress_sink::ProgressSink;
use crate::session::tap::{MessageTap, Tap, TappedMessage};

/// How progress is shown on stderr.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// A terminal: one line redrawn in place.
    Bar,
    /// A pipe or a file: a line per tenth and per station.
    Lines,
    /// `--quiet`: nothing.
    Quiet,
}

impl Mode {
    /// `Bar` when stderr is a terminal, else `Lines`; `Quiet` when asked.
    pub fn for_stderr(quiet: bool) -> Mode {
        if quiet {
            Mode::Quiet
        } else if std::io::stderr().is_terminal() {
            Mode::Bar
        } else {
            Mode::Lines
        }
    }
}

/// When line-by-line progress writes a line: at each tenth of the total crossed (each line
/// names the station), and when the first station begins. A log (`for_log`) also has a line
/// for every station that begins away from the last line (more than a twentieth of the total
/// from it; a station that begins near it is named in the next one).
#[derive(Debug, Clone, Default)]
pub struct Cadence {
    every_station: bool,
    tenths: u64,
    last_line_done: Option<u64>,
    station: Option<String>,
    done: u64,
    total: u64,
}

impl Cadence {
    /// The daemon's log: a line per tenth and per station.
    pub fn for_log() -> Cadence {
        Cadence {
            every_station: true,
            ..Cadence::default()
        }
    }

    /// Points done of the total; true when a line is due.
    pub fn progress(&mut self, done: u64, total: u64) -> bool {
        self.done = done;
        self.total = total;
        if total == 0 {
            return false;
        }
        let tenths = done.min(total) * 10 / total;
        if tenths > self.tenths {
            self.tenths = tenths;
            self.last_line_done = Some(done);
            return true;
        }
        false
    }

    /// A station begins; true when a line is due.
    pub fn station(&mut self, station: &str) -> bool {
        if self.station.as_deref() == Some(station) {
            return false;
        }
        self.station = Some(station.to_owned());
        let due = match self.last_line_done {
            None => true,
            Some(last) => self.every_station && self.done.abs_diff(last) * 20 >= self.total.max(1),
        };
        if due {
            self.last_line_done = Some(self.done);
        }
        due
    }

    pub fn current_station(&self) -> Option<&str> {
        self.station.as_deref()
    }
}

struct State {
    mode: Mode,
    bar: Option<ProgressBar>,
    prefix: String,
    unit: String,
    cadence: Cadence,
    /// The first count seen and when: the rate is measured from it (a followed job or a
    /// resumed run starts part-way).
    first: Option<(u64, Instant)>,
    done: u64,
    total: u64,
    point: Option<String>,
}

impl State {
    fn rate_per_s(&self) -> Option<f64> {
        let (first, at) = self.first?;
        let elapsed = at.elapsed().as_secs_f64();
        (elapsed > 0.5 && self.done > first).then(|| (self.done - first) as f64 / elapsed)
    }

    fn status(&self) -> String {
        let mut parts = Vec::new();
        if let Some(rate) = self.rate_per_s() {
            parts.push(format!("{rate:.1} {}/s", self.unit));
            if self.total >= self.done {
                parts.push(format!(
                    "about {} left",
                    duration_text((self.total - self.done) as f64 / rate)
                ));
            }
        }
        if let Some(station) = self.cadence.current_station() {
            parts.push(format!("station {station}"));
        }
        if let Some(point) = &self.point {
            parts.push(point.clone());
        }
        parts.join(", ")
    }

    fn line(&self) -> String {
        let percent = if self.total > 0 {
            format!(" ({:.0} %)", 100.0 * self.done as f64 / self.total as f64)
        } else {
            String::new()
        };
        let status = self.status();
        let status = if status.is_empty() {
            status
        } else {
            format!(", {status}")
        };
        format!(
            "{}: {}/{} {}{percent}{status}",
            self.prefix, self.done, self.total, self.unit
        )
    }

    fn redraw(&self) {
        if let Some(bar) = &self.bar {
            if bar.is_hidden() && self.total > 0 {
                bar.set_draw_target(ProgressDrawTarget::stderr());
            }
            bar.set_length(self.total);
            bar.set_position(self.done);
            bar.set_message(self.status());
        }
    }
}

/// The progress of one piece of work counted in `unit`s (points, postures, …). Cheap to clone;
/// every clone reports to the same line.
#[derive(Clone)]
pub struct Progress {
    state: Arc<Mutex<State>>,
}

impl Progress {
    /// `prefix` names the work ("run", "job 3"), `unit` what is counted.
    pub fn new(mode: Mode, prefix: &str, unit: &str) -> Progress {
        let bar = (mode == Mode::Bar).then(|| {
            // Drawn from the first count on (an empty bar of 0/0 says nothing).
            let bar = ProgressBar::with_draw_target(Some(0), ProgressDrawTarget::hidden());
            let template = format!("{{prefix}} {{bar:24}} {{pos}}/{{len}} {unit} {{wide_msg}}");
            if let Ok(style) = ProgressStyle::with_template(&template) {
                bar.set_style(style.progress_chars("█▌ "));
            }
            bar.set_prefix(prefix.to_owned());
            bar
        });
        Progress {
            state: Arc::new(Mutex::new(State {
                mode,
                bar,
                prefix: prefix.to_owned(),
                unit: unit.to_owned(),
                cadence: Cadence::default(),
                first: None,
                done: 0,
                total: 0,
                point: None,
            })),
        }
    }

    fn with<T>(&self, f: impl FnOnce(&mut State) -> T) -> Option<T> {
        self.state.lock().ok().map(|mut s| f(&mut s))
    }

    /// `done` of `total` finished.
    pub fn update(&self, done: u64, total: u64) {
        self.with(|s| {
            s.first.get_or_insert((done, Instant::now()));
            s.done = done;
            s.total = total;
            let due = s.cadence.progress(done, total);
            match s.mode {
                Mode::Bar => s.redraw(),
                Mode::Lines if due => crate::console::write_err(format_args!("{}\n", s.line())),
                _ => {}
            }
        });
    }

    /// The station being measured now.
    pub fn station(&self, station: &str) {
        self.with(|s| {
            let due = s.cadence.station(station);
            s.point = None;
            match s.mode {
                Mode::Bar => s.redraw(),
                Mode::Lines if due => crate::console::write_err(format_args!("{}\n", s.line())),
                _ => {}
            }
        });
    }

    /// The point being measured now (shown on the terminal's line only).
    pub fn point(&self, label: String) {
        self.with(|s| {
            if s.mode == Mode::Bar {
                s.point = Some(label);
                s.redraw();
            }
        });
    }

    /// A line that must be seen (a state change, a fault, a prompt), above the progress line.
    pub fn println(&self, text: &str) {
        self.with(|s| match (&s.bar, s.mode) {
            (Some(bar), _) => bar.println(text),
            (None, Mode::Lines) => crate::console::write_err(format_args!("{text}\n")),
            _ => {}
        });
    }

    /// The work ended: the terminal's line is cleared.
    pub fn finish(&self) {
        self.with(|s| {
            if let Some(bar) = &s.bar {
                bar.finish_and_clear();
            }
        });
    }

    /// A sink for a run's `RunControl::progress`.
    pub fn sink(&self) -> ProgressSink {
        let progress = self.clone();
        ProgressSink::new(move |done, total| progress.update(done, total))
    }

    /// A recorder tap that shows the station and point each run event names, then hands the
    /// message on to `next` (the live view).
    pub fn tap(&self, next: Tap) -> Tap {
        Tap::new(Arc::new(EventTap {
            progress: self.clone(),
            next,
        }))
    }
}

struct EventTap {
    progress: Progress,
    next: Tap,
}

impl MessageTap for EventTap {
    fn message(&self, message: &TappedMessage<'_>) {
        if let Some(next) = &self.next.0 {
            next.message(message);
        }
        if message.channel.topic != crate::session::messages::TOPIC_EVENT {
            return;
        }
        let Ok(event) = serde_json::from_slice::<serde_json::Value>(message.data) else {
            return;
        };
        let text = |key: &str| event.get(key).and_then(|v| v.as_str());
        let number = |key: &str| event.get(key).and_then(|v| v.as_u64());
        match text("kind") {
            Some("station_begin") => {
                if let Some(station) = text("station") {
                    self.progress.station(station);
                }
            }
            Some("point_begin") | Some("probe_point_begin") => {
                if let Some(point) = number("point") {
                    let pass = number("pass").map_or(String::new(), |p| format!(" pass {p}"));
                    self.progress.point(format!("point {point}{pass}"));
                }
            }
            _ => {}
        }
    }
}

/// A phase without a count (a solve, a diagnosis): a spinner with the phase and the time
/// spent, on a terminal only. Finish it with `finish_and_clear`.
pub fn spinner(mode: Mode, phase: &str) -> ProgressBar {
    if mode != Mode::Bar {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::with_draw_target(None, ProgressDrawTarget::stderr());
    if let Ok(style) = ProgressStyle::with_template("{spinner} {msg} ({elapsed})") {
        bar.set_style(style);
    }
    bar.set_message(phase.to_owned());
    bar.enable_steady_tick(Duration::from_millis(120));
    bar
}

/// "12 s", "3 min 05 s", "1 h 02 min".
pub fn duration_text(seconds: f64) -> String {
    if !seconds.is_finite() || seconds < 0.0 {
        return "?".into();
    }
    let s = seconds.round() as u64;
    match s {
        0..60 => format!("{s} s"),
        60..3600 => format!("{} min {:02} s", s / 60, s % 60),
        _ => format!("{} h {:02} min", s / 3600, (s % 3600) / 60),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The demo's shape: 1000 points, a station every 200 (its event, through the recorder's
    /// thread, a few points late): a line per tenth and the first station; a log also has
    /// the stations that begin away from a tenth's line.
    #[test]
    fn a_line_per_tenth_and_per_station_never_per_point() {
        for (cadence, station_lag, want) in [
            (Cadence::default(), 2, 11),
            (Cadence::for_log(), 2, 11),
            (Cadence::for_log(), 160, 15),
        ] {
            let mut cadence = cadence;
            let mut lines = 0;
            for done in 0..=1000u64 {
                if cadence.progress(done, 1000) {
                    lines += 1;
                }
                if done % 200 == station_lag % 200
                    && done < 1000
                    && cadence.station(&format!("s{}", done / 200))
                {
                    lines += 1;
                }
            }
            assert_eq!(
                lines, want,
                "{cadence:?}, stations {station_lag} points late"
            );
        }
    }

    #[test]
    fn durations_read_as_a_person_says_them() {
        assert_eq!(duration_text(12.4), "12 s");
        assert_eq!(duration_text(185.0), "3 min 05 s");
        assert_eq!(duration_text(3720.0), "1 h 02 min");
    }
}
