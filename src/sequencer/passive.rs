//! Passive mode: the machine runs the NC program of `geocal export-nc` by itself; the
//! sequencer only watches the tracer, matches each stop to the expected point and records it.
//!
//! `StopMatcher` is sans-I/O: fed samples, it says when to home, when a point's window begins
//! and ends, and which stops were not planned (`unplanned_stop` events). A stop is the
//! expected point when its length, relative to the last homing at point 0, is within a
//! tolerance of the length the station hint predicts (the tolerance covers the hint's error),
//! and when it lasts the dwell; otherwise it is reported and skipped.

use async_trait::async_trait;
use geocal_drivers::{AxisPositions, DeviceError, Machine, MachineState};
use nalgebra::Vector3;

use super::{Progress, RunSummary, Sequencer, SequencerError, MAX_MOVE_S};
use crate::extract::{Stillstand, StillstandDetector};
use crate::plan::{Plan, PlanStation, PlanTarget};
use crate::session::messages::RunEvent;

/// The machine of a passive run: geocal never commands it.
pub struct PassiveMachine {
    pub id: String,
}

#[async_trait]
impl Machine for PassiveMachine {
    fn id(&self) -> &str {
        &self.id
    }
    async fn start_move(&mut self, _target: &AxisPositions) -> Result<(), DeviceError> {
        Err(DeviceError::Rejected {
            device: self.id.clone(),
            message: "passive machine: it runs its NC program (geocal export-nc) by itself".into(),
        })
    }
    async fn state(&mut self) -> Result<MachineState, DeviceError> {
        Ok(MachineState::Moving)
    }
}

/// One expected stop: a plan point of a pass, the length predicted there relative to the
/// homing at point 0, and the tolerance of that prediction.
#[derive(Debug, Clone, PartialEq)]
pub struct Expected {
    pub pass: usize,
    pub point: usize,
    pub length_m: f64,
    pub tolerance_m: f64,
}

/// The expected stops of one station and target, every pass in order.
pub fn expected_stops(
    plan: &Plan,
    station: &PlanStation,
    target: &PlanTarget,
    hint_tolerance_m: f64,
) -> Vec<Expected> {
    let at = |point: usize| Vector3::from(plan.nominal_m(point, target));
    let mut out = Vec::new();
    for (pass, &direction) in plan.passes.iter().enumerate() {
        for point in plan.pass_order(direction) {
            let (length_m, tolerance_m) = match station.hint_m {
                Some(h) => {
                    let h = Vector3::from(h);
                    let (d0, dk) = (at(0) - h, at(point) - h);
                    let du = (dk.normalize() - d0.normalize()).norm();
                    (dk.norm() - d0.norm(), du * hint_tolerance_m + 1e-3)
                }
                None => (0.0, f64::INFINITY),
            };
            out.push(Expected {
                pass,
                point,
                length_m,
                tolerance_m,
            });
        }
    }
    out
}

/// What the sequencer must do after a sample.
#[derive(Debug, Clone, PartialEq)]
pub enum Action {
    /// The machine stopped at point 0: home the tracer.
    Home,
    /// The window of expected stop `index` begins.
    Begin { index: usize },
    /// Its dwell is complete.
    End { index: usize },
    /// A stop that is not expected stop `index` (or left before its dwell was complete).
    Unplanned { index: usize, message: String },
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum State {
    /// Until the length leaves `from_m` by more than the stillstand tolerance.
    WaitMove {
        from_m: f64,
    },
    WaitStop,
    /// Homed at point 0: wait until settled again (`first` length after homing).
    Homing {
        first_m: Option<f64>,
    },
    InWindow {
        begin_s: f64,
    },
}

pub struct StopMatcher {
    detector: StillstandDetector,
    tolerance_m: f64,
    dwell_s: f64,
    expected: Vec<Expected>,
    next: usize,
    /// The next stop at point 0 is homed on without a length check (no valid homing yet).
    unchecked_home: bool,
    state: Option<State>,
}

impl StopMatcher {
    pub fn new(window_s: f64, tolerance_m: f64, dwell_s: f64) -> Self {
        Self {
            detector: StillstandDetector::new(window_s, tolerance_m),
            tolerance_m,
            dwell_s,
            expected: Vec::new(),
            next: 0,
            unchecked_home: true,
            state: None,
        }
    }

    /// A new station or target: these stops follow, the first one at point 0. The machine
    /// may already stand there (no motion first): the first stillstand is taken as point 0.
    pub fn start_block(&mut self, expected: Vec<Expected>) {
        self.expected = expected;
        self.next = 0;
        self.unchecked_home = true;
        self.state = Some(State::WaitStop);
        self.detector.reset();
    }

    pub fn done(&self) -> bool {
        self.next >= self.expected.len()
    }

    pub fn expected(&self, index: usize) -> Option<&Expected> {
        self.expected.get(index)
    }

    /// Index of the stop expected next.
    pub fn next_index(&self) -> usize {
        self.next
    }

    pub fn push(&mut self, t_s: f64, length_m: f64) -> Option<Action> {
        let state = self.detector.push(t_s, length_m);
        let settled = matches!(state, Stillstand::Settled { .. });
        let expected = self.expected.get(self.next)?;
        match self.state.unwrap_or(State::WaitMove { from_m: length_m }) {
            State::WaitMove { from_m } => {
                if (length_m - from_m).abs() > self.tolerance_m {
                    self.state = Some(State::WaitStop);
                    self.detector.reset();
                } else {
                    self.state = Some(State::WaitMove { from_m });
                }
                None
            }
            State::WaitStop => {
                if !settled {
                    return None;
                }
                let first = self.unchecked_home && expected.point == 0;
                let off_m = length_m - expected.length_m;
                if !first && off_m.abs() > expected.tolerance_m {
                    self.state = Some(State::WaitMove { from_m: length_m });
                    return Some(Action::Unplanned {
                        index: self.next,
                        message: format!(
                            "stop at length {length_m:.6} m; point {} of pass {} was expected at \
                             {:.6} m ± {:.6} m",
                            expected.point, expected.pass, expected.length_m, expected.tolerance_m
                        ),
                    });
                }
                if expected.point == 0 {
                    self.state = Some(State::Homing { first_m: None });
                    self.detector.reset();
                    return Some(Action::Home);
                }
                self.state = Some(State::InWindow { begin_s: t_s });
                Some(Action::Begin { index: self.next })
            }
            State::Homing { first_m } => {
                let first_m = first_m.unwrap_or(length_m);
                if (length_m - first_m).abs() > self.tolerance_m {
                    // It moved on: that was not point 0 (and the homing is void).
                    self.unchecked_home = true;
                    self.state = Some(State::WaitStop);
                    self.detector.reset();
                    return Some(Action::Unplanned {
                        index: self.next,
                        message: "the machine moved on while the tracer was homed there: not \
                                  point 0"
                            .into(),
                    });
                }
                if settled {
                    self.unchecked_home = false;
                    self.state = Some(State::InWindow { begin_s: t_s });
                    return Some(Action::Begin { index: self.next });
                }
                self.state = Some(State::Homing {
                    first_m: Some(first_m),
                });
                None
            }
            State::InWindow { begin_s } => {
                if !settled {
                    if expected.point == 0 {
                        self.unchecked_home = true;
                    }
                    self.state = Some(State::WaitStop);
                    self.detector.reset();
                    return Some(Action::Unplanned {
                        index: self.next,
                        message: format!(
                            "the machine moved on after {:.3} s, before the dwell of {:.3} s",
                            t_s - begin_s,
                            self.dwell_s
                        ),
                    });
                }
                if t_s - begin_s < self.dwell_s {
                    return None;
                }
                let index = self.next;
                self.next += 1;
                self.state = Some(State::WaitMove { from_m: length_m });
                Some(Action::End { index })
            }
        }
    }
}

impl Sequencer<'_> {
    /// Passive mode: per station and target, follow the tracer and match its stops.
    pub(super) async fn run_passive(
        &mut self,
        hint_tolerance_m: f64,
        progress: Progress<'_>,
    ) -> Result<RunSummary, SequencerError> {
        let plan = self.plan;
        let total =
            (plan.stations.len() * plan.targets.len() * plan.passes.len() * plan.points.len())
                as u64;
        let mut matcher = StopMatcher::new(
            plan.stillstand_window_s,
            plan.stillstand_tolerance_m,
            plan.dwell_s,
        );
        let mut mounted: Option<&PlanTarget> = None;
        let mut done = 0;
        for (station_index, station) in plan.stations.iter().enumerate() {
            self.station = station.id.clone();
            self.event(RunEvent::StationBegin {
                station: station.id.as_str().into(),
                station_index,
                hint_m: station.hint_m,
            });
            self.devices
                .operator
                .place_station(station_index, &station.id, station.hint_m)
                .await?;
            for target in &plan.targets {
                if mounted != Some(target) {
                    self.devices
                        .operator
                        .mount_target(&target.id, target.offset_m)
                        .await?;
                    mounted = Some(target);
                }
                matcher.start_block(expected_stops(plan, station, target, hint_tolerance_m));
                let mut last_action_s = self.last_sample.map_or(0.0, |s| s.t_s);
                while !matcher.done() {
                    let sample = self.sample().await?;
                    if !sample.tracking {
                        return Err(SequencerError::NoBeam {
                            station: station.id.clone(),
                            waited_s: 0.0,
                        });
                    }
                    let Some(action) = matcher.push(sample.t_s, sample.length_m) else {
                        if sample.t_s - last_action_s > MAX_MOVE_S {
                            return Err(SequencerError::NoArrival {
                                point: matcher
                                    .expected(matcher.next_index())
                                    .map_or(0, |e| e.point),
                                waited_s: sample.t_s - last_action_s,
                            });
                        }
                        continue;
                    };
                    last_action_s = sample.t_s;
                    match action {
                        Action::Home => self.home_tracer().await?,
                        Action::Begin { index } => {
                            if let Some(e) = matcher.expected(index).cloned() {
                                self.note_command(plan.points[e.point].axes_m);
                                let event =
                                    self.point_begin_event(&station.id, target, e.point, e.pass);
                                self.event(event);
                            }
                        }
                        Action::End { index } => {
                            if let Some(e) = matcher.expected(index).cloned() {
                                self.event(RunEvent::PointEnd {
                                    station: station.id.as_str().into(),
                                    point: e.point,
                                    pass: e.pass,
                                });
                                self.recorder.checkpoint();
                                self.summary.points_measured += 1;
                                done += 1;
                                progress(done, total);
                                super::control::cancellation_point().await;
                            }
                        }
                        Action::Unplanned { index, message } => {
                            let e = matcher.expected(index).cloned();
                            self.event(RunEvent::UnplannedStop {
                                station: station.id.as_str().into(),
                                target: target.id.as_str().into(),
                                pass: e.as_ref().map_or(0, |e| e.pass),
                                point: e.as_ref().map_or(0, |e| e.point),
                                message,
                            });
                        }
                    }
                }
            }
            self.event(RunEvent::StationEnd {
                station: station.id.as_str().into(),
            });
        }
        self.poll_environment().await?;
        Ok(self.summary.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A stream of stops: (length, duration) pairs with moves of 1 s between them.
    fn feed(m: &mut StopMatcher, stops: &[(f64, f64)]) -> Vec<Action> {
        let mut out = vec![];
        let mut t = 0.0;
        let mut at = 0.0;
        let mut homed_at = 0.0;
        for &(to, dwell) in stops {
            for k in 1..=10 {
                t += 0.1;
                let l = at + (to - at) * k as f64 / 10.0 - homed_at;
                out.extend(m.push(t, l));
            }
            at = to;
            let end = t + dwell;
            while t < end {
                t += 0.1;
                if let Some(a) = m.push(t, at - homed_at) {
                    if a == Action::Home {
                        homed_at = at;
                    }
                    out.push(a);
                }
            }
        }
        out
    }

    fn exp(point: usize, length_m: f64) -> Expected {
        Expected {
            pass: 0,
            point,
            length_m,
            tolerance_m: 0.01,
        }
    }

    #[test]
    fn planned_stops_are_matched_and_unplanned_ones_reported() {
        let mut m = StopMatcher::new(0.5, 1e-6, 1.0);
        m.start_block(vec![exp(0, 0.0), exp(1, 0.3), exp(2, 0.5)]);
        // Point 0 at 1.0 m (before homing), a pause at 1.15 m (length 0.15 after homing: not
        // point 1's 0.3), point 1, a short pause at 1.4 m (length 0.4 mid-move), point 2.
        let actions = feed(
            &mut m,
            &[(1.0, 3.0), (1.15, 2.0), (1.3, 2.0), (1.4, 0.8), (1.5, 2.0)],
        );
        let kinds: Vec<String> = actions
            .iter()
            .map(|a| match a {
                Action::Home => "home".into(),
                Action::Begin { index } => format!("begin{index}"),
                Action::End { index } => format!("end{index}"),
                Action::Unplanned { index, .. } => format!("unplanned{index}"),
            })
            .collect();
        assert_eq!(
            kinds,
            [
                "home",
                "begin0",
                "end0",
                "unplanned1",
                "begin1",
                "end1",
                "unplanned2",
                "begin2",
                "end2"
            ]
        );
        assert!(m.done());
    }

    #[test]
    fn a_stop_that_matches_but_leaves_early_is_reported() {
        let mut m = StopMatcher::new(0.5, 1e-6, 1.0);
        m.start_block(vec![exp(0, 0.0), exp(1, 0.3)]);
        // Within tolerance of point 1 (0.295) but only 0.8 s: begin, then unplanned.
        let actions = feed(&mut m, &[(1.0, 3.0), (1.295, 0.8), (1.3, 2.0)]);
        assert!(matches!(actions[3], Action::Begin { index: 1 }));
        assert!(matches!(actions[4], Action::Unplanned { index: 1, .. }));
        assert!(matches!(actions[6], Action::End { index: 1 }));
    }
}
