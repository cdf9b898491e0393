//! Four-axis method (tracer standing on a rotary table): multilateration of every station, a
//! circle through the table stations (the table axis), and the true angle of every table step.

use nalgebra::{DMatrix, Vector3};
use serde::{Deserialize, Serialize};

use crate::method::multilateration::{self, MultilaterationError, MultilaterationResults};
use crate::session::messages::RunEvent;
use crate::session::reader::Session;
use crate::solve::circle::{fit_circle, CircleError};

pub const KIND: &str = "rotary_tracer";

#[derive(Debug, thiserror::Error)]
pub enum RotaryTracerError {
    #[error(transparent)]
    Multilateration(#[from] MultilaterationError),
    #[error("no `rotation` events in the session: no station stood on a rotary table")]
    NoRotations,
    #[error("`rotation` events name two tables, `{0}` and `{1}`: expected one")]
    SeveralTables(String, String),
    #[error(
        "`rotation` event for table `{table}` outside any station (at log_time {log_time_ns} ns)"
    )]
    RotationOutsideStation { table: String, log_time_ns: u64 },
    #[error("table station `{0}` has no solved position (no settled points measured from it)")]
    StationNotSolved(String),
    #[error("{found} table stations: the circle through them needs at least 3")]
    TooFewTableStations { found: usize },
    #[error("circle through the table stations: {0}")]
    Circle(#[from] CircleError),
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct RotaryTracerResults {
    /// Stations and points, as a multilateration (with `kind` = "rotary_tracer").
    #[serde(flatten)]
    pub multilateration: MultilaterationResults,
    pub rotary: RotaryResult,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct RotaryResult {
    pub table: String,
    /// The circle's centre: the point of the table axis in the plane of the table stations.
    pub axis_point_m: [f64; 3],
    pub axis_point_sigma_m: [f64; 3],
    /// Unit axis direction; positive angles turn right-handed about it (the commanded sense).
    pub axis_direction: [f64; 3],
    pub axis_direction_sigma: [f64; 3],
    /// Distance of the tracer on the table from the axis.
    pub radius_m: f64,
    pub radius_sigma_m: f64,
    /// RMS distance of the table stations from the fitted circle.
    pub circle_residual_rms_m: f64,
    /// The station the step angles are measured from.
    pub reference_station: String,
    pub note: String,
    pub steps: Vec<StepResult>,
    /// Covariance of the steps' `error_rad`, rad², rows and columns in the order of `steps`
    /// (the reference station's row and column are 0): the steps share the reference station,
    /// so their errors are correlated. Empty in results written before it was reported.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub error_covariance_rad2: Vec<Vec<f64>>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct StepResult {
    pub station: String,
    pub commanded_rad: f64,
    /// The table's encoder angle in position, when the session recorded it.
    pub encoder_rad: Option<f64>,
    /// The true table angle: the reference station's commanded angle plus the angle the
    /// station turned about the fitted axis from the reference station.
    pub measured_rad: f64,
    /// measured − commanded: the angular positioning error relative to the reference station.
    pub error_rad: f64,
    /// Standard uncertainty of `measured_rad` and `error_rad` (0 for the reference station).
    pub sigma_rad: f64,
    /// The side the table approached `commanded_rad` from: +1 turning positive, −1 negative
    /// (from the overshoot angle, or the previous station's angle); absent when unknown.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub approach: Option<i8>,
}

/// One table station as the session's events describe it.
#[derive(Debug, Clone)]
struct TableStation {
    station: String,
    commanded_rad: f64,
    via_rad: Option<f64>,
    /// Log times between which the table was (being) in position for this station.
    from_ns: u64,
    until_ns: u64,
}

fn table_stations(session: &Session) -> Result<(String, Vec<TableStation>), RotaryTracerError> {
    let mut table: Option<String> = None;
    let mut current: Option<String> = None;
    let mut out: Vec<TableStation> = Vec::new();
    for stamped in &session.events {
        match &stamped.msg {
            RunEvent::StationBegin { station, .. } => {
                if let Some(last) = out.last_mut() {
                    last.until_ns = last.until_ns.min(stamped.log_time_ns);
                }
                current = Some(station.to_string());
            }
            RunEvent::StationEnd { .. } => {
                if let Some(last) = out.last_mut() {
                    last.until_ns = last.until_ns.min(stamped.log_time_ns);
                }
                current = None;
            }
            RunEvent::Rotation {
                table: t,
                commanded_rad,
                via_rad,
            } => {
                match &table {
                    Some(known) if known != t => {
                        return Err(RotaryTracerError::SeveralTables(known.clone(), t.clone()))
                    }
                    _ => table = Some(t.clone()),
                }
                let Some(station) = &current else {
                    return Err(RotaryTracerError::RotationOutsideStation {
                        table: t.clone(),
                        log_time_ns: stamped.log_time_ns,
                    });
                };
                // A repeated rotation within a station (a retry) replaces the earlier one.
                if out.last().is_some_and(|s| &s.station == station) {
                    out.pop();
                }
                out.push(TableStation {
                    station: station.clone(),
                    commanded_rad: *commanded_rad,
                    via_rad: *via_rad,
                    from_ns: stamped.log_time_ns,
                    until_ns: u64::MAX,
                });
            }
            _ => {}
        }
    }
    let table = table.ok_or(RotaryTracerError::NoRotations)?;
    Ok((table, out))
}

/// The encoder angle the table reported in position for a station, if recorded.
fn encoder_rad(session: &Session, table: &str, s: &TableStation) -> Option<f64> {
    session
        .rotary
        .get(table)?
        .iter()
        .filter(|r| r.log_time_ns >= s.from_ns && r.log_time_ns <= s.until_ns)
        .filter(|r| r.msg.in_position && r.msg.commanded_rad == s.commanded_rad)
        .filter_map(|r| r.msg.encoder_rad)
        .next_back()
}

/// The side station `k` was approached from: from its overshoot angle, else from the
/// previous table station's angle; None when the table did not move or nothing came before.
fn approach(on_table: &[TableStation], k: usize) -> Option<i8> {
    let from = on_table[k]
        .via_rad
        .or_else(|| k.checked_sub(1).map(|p| on_table[p].commanded_rad))?;
    let turn = on_table[k].commanded_rad - from;
    (turn != 0.0).then_some(if turn > 0.0 { 1 } else { -1 })
}

fn wrap_pi(a: f64) -> f64 {
    let w = a.rem_euclid(std::f64::consts::TAU);
    if w > std::f64::consts::PI {
        w - std::f64::consts::TAU
    } else {
        w
    }
}

fn sqrt_diag(m: &nalgebra::Matrix3<f64>) -> [f64; 3] {
    [0, 1, 2].map(|k| m[(k, k)].max(0.0).sqrt())
}

/// The covariance of the `count` stations' angles from station 0 (the reference): row and
/// column 0 are 0.
fn step_error_covariance(fit: &crate::solve::circle::CircleFit, count: usize) -> Vec<Vec<f64>> {
    (0..count)
        .map(|j| {
            (0..count)
                .map(|k| {
                    if j == 0 || k == 0 {
                        0.0
                    } else {
                        fit.angle_covariance(0, j, k)
                    }
                })
                .collect()
        })
        .collect()
}

/// Solve a rotary-tracer session.
pub fn solve(
    session: &Session,
    settings: &crate::method::SolveSettings,
) -> Result<RotaryTracerResults, RotaryTracerError> {
    let (results, solution) = multilateration::solve_detailed(session, settings)?;
    table_axis(session, results, &solution)
}

/// Solve a rotary-tracer session file streamed, as `solve` solves it read whole: the tracer
/// samples go straight to the extraction; the table reads the station and rotation events
/// and the table's recorded states. None when the file cannot be streamed exactly.
pub fn solve_file_streaming(
    path: &std::path::Path,
    settings: &crate::method::SolveSettings,
) -> Option<Result<RotaryTracerResults, RotaryTracerError>> {
    let solved =
        multilateration::solve_file_streaming_detailed(path, settings, KIND, is_table_event)?;
    Some(
        solved
            .map_err(RotaryTracerError::from)
            .and_then(|(results, solution, session)| table_axis(&session, results, &solution)),
    )
}

/// The events `table_stations` reads.
fn is_table_event(event: &RunEvent) -> bool {
    matches!(
        event,
        RunEvent::StationBegin { .. } | RunEvent::StationEnd { .. } | RunEvent::Rotation { .. }
    )
}

/// The table's axis and step angles from the stations' multilateration (`results`,
/// `solution`), the session's table events and recorded table states.
fn table_axis(
    session: &Session,
    mut results: MultilaterationResults,
    solution: &crate::solve::multilateration::MultilaterationSolution,
) -> Result<RotaryTracerResults, RotaryTracerError> {
    results.kind = KIND.into();
    let (table, on_table) = table_stations(session)?;
    if on_table.len() < 3 {
        return Err(RotaryTracerError::TooFewTableStations {
            found: on_table.len(),
        });
    }
    let index: Vec<usize> = on_table
        .iter()
        .map(|s| {
            results
                .stations
                .iter()
                .position(|r| r.id == s.station)
                .ok_or_else(|| RotaryTracerError::StationNotSolved(s.station.clone()))
        })
        .collect::<Result<_, _>>()?;
    let points: Vec<Vector3<f64>> = index.iter().map(|&j| solution.stations[j]).collect();
    let joint = &solution.station_joint_covariance;
    let cov = DMatrix::from_fn(3 * index.len(), 3 * index.len(), |r, c| {
        joint[(3 * index[r / 3] + r % 3, 3 * index[c / 3] + c % 3)]
    });
    let commanded_step = |k: usize| on_table[k].commanded_rad - on_table[0].commanded_rad;
    // The sense of rotation comes from the commands: the normal that makes the measured steps
    // agree with the commanded ones.
    let mut fit = fit_circle(&points, Some(&cov), None)?;
    let mismatch = |fit: &crate::solve::circle::CircleFit| -> f64 {
        (1..points.len())
            .map(|k| wrap_pi(fit.angle_from(0, k).0 - commanded_step(k)).abs())
            .sum()
    };
    let flipped = fit_circle(&points, Some(&cov), Some(-fit.normal.into_inner()))?;
    if mismatch(&flipped) < mismatch(&fit) {
        fit = flipped;
    }
    let error_covariance_rad2 = step_error_covariance(&fit, on_table.len());
    let steps = on_table
        .iter()
        .enumerate()
        .map(|(k, s)| {
            let (turned_rad, sigma_rad) = if k == 0 {
                (0.0, 0.0)
            } else {
                fit.angle_from(0, k)
            };
            let error_rad = wrap_pi(turned_rad - commanded_step(k));
            StepResult {
                station: s.station.clone(),
                commanded_rad: s.commanded_rad,
                encoder_rad: encoder_rad(session, &table, s),
                measured_rad: s.commanded_rad + error_rad,
                error_rad,
                sigma_rad,
                approach: approach(&on_table, k),
            }
        })
        .collect();
    let rotary = RotaryResult {
        table,
        axis_point_m: fit.centre_m.into(),
        axis_point_sigma_m: sqrt_diag(&fit.centre_covariance()),
        axis_direction: fit.normal.into_inner().into(),
        axis_direction_sigma: sqrt_diag(&fit.normal_covariance()),
        radius_m: fit.radius_m,
        radius_sigma_m: fit.radius_sigma_m(),
        circle_residual_rms_m: fit.residual_rms_m,
        reference_station: on_table[0].station.clone(),
        note: "least-squares circle (plane, centre, radius) through the multilateration \
               positions of the table stations; step angles about its axis from the reference \
               station, error = measured - commanded (0 at the reference by definition); \
               sigmas propagated from the stations' joint covariance"
            .into(),
        steps,
        error_covariance_rad2,
    };
    Ok(RotaryTracerResults {
        multilateration: results,
        rotary,
    })
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use super::*;
    use crate::session::messages::RotaryStateSample;
    use crate::session::reader::testutil::header;
    use crate::session::reader::{Completeness, Stamped};

    fn session(events: Vec<RunEvent>, rotary: Vec<(u64, RotaryStateSample)>) -> Session {
        let stamp = |(i, msg)| Stamped {
            log_time_ns: 10 * i as u64,
            publish_time_ns: 10 * i as u64,
            msg,
        };
        Session {
            header: header(),
            tracers: BTreeMap::new(),
            env: BTreeMap::new(),
            rotary: BTreeMap::from([(
                "c".to_string(),
                rotary
                    .into_iter()
                    .map(|(t, msg)| Stamped {
                        log_time_ns: t,
                        publish_time_ns: t,
                        msg,
                    })
                    .collect(),
            )]),
            machines: BTreeMap::new(),
            probes: BTreeMap::new(),
            events: events.into_iter().enumerate().map(stamp).collect(),
            topics: BTreeMap::new(),
            completeness: Completeness::Complete,
            damaged: Vec::new(),
            lost_before_repair: Vec::new(),
            skipped: 0,
            ignored: 0,
        }
    }

    fn begin(station: &str) -> RunEvent {
        RunEvent::StationBegin {
            station: station.into(),
            station_index: 0,
            hint_m: None,
        }
    }
    fn end(station: &str) -> RunEvent {
        RunEvent::StationEnd {
            station: station.into(),
        }
    }
    fn rotation(table: &str, commanded_rad: f64) -> RunEvent {
        RunEvent::Rotation {
            table: table.into(),
            commanded_rad,
            via_rad: None,
        }
    }
    fn state(commanded_rad: f64, encoder: Option<f64>) -> RotaryStateSample {
        RotaryStateSample {
            t_s: 0.0,
            commanded_rad,
            encoder_rad: encoder,
            in_position: encoder.is_some(),
        }
    }

    #[test]
    fn table_stations_come_from_rotation_events() {
        let s = session(
            vec![
                begin("c01"),       // 0
                rotation("c", 0.0), // 10
                end("c01"),         // 20
                begin("c02"),       // 30
                rotation("c", 0.4), // 40: retried below
                rotation("c", 0.5), // 50
                end("c02"),         // 60
                begin("s13"),       // 70
                end("s13"),         // 80
            ],
            vec![
                (12, state(0.0, Some(0.0))),
                (52, state(0.5, None)),
                (55, state(0.5, Some(0.5001))),
                (75, state(0.5, Some(9.0))),
            ],
        );
        let (table, stations) = table_stations(&s).expect("table stations");
        assert_eq!(table, "c");
        let got: Vec<(&str, f64)> = stations
            .iter()
            .map(|t| (t.station.as_str(), t.commanded_rad))
            .collect();
        assert_eq!(got, [("c01", 0.0), ("c02", 0.5)]);
        assert_eq!(encoder_rad(&s, "c", &stations[0]), Some(0.0));
        // Only states inside the station count (not the one during s13).
        assert_eq!(encoder_rad(&s, "c", &stations[1]), Some(0.5001));
    }

    #[test]
    fn inconsistent_rotations_are_errors() {
        let none = session(vec![begin("s1"), end("s1")], vec![]);
        assert!(matches!(
            table_stations(&none),
            Err(RotaryTracerError::NoRotations)
        ));
        let outside = session(vec![rotation("c", 0.1), begin("s1")], vec![]);
        assert!(matches!(
            table_stations(&outside),
            Err(RotaryTracerError::RotationOutsideStation { .. })
        ));
        let two = session(
            vec![
                begin("a"),
                rotation("c", 0.1),
                end("a"),
                begin("b"),
                rotation("b", 0.2),
            ],
            vec![],
        );
        let err = table_stations(&two).expect_err("two tables");
        assert!(err.to_string().contains("`c`") && err.to_string().contains("`b`"));
    }

    #[test]
    fn approach_comes_from_the_overshoot_or_the_previous_angle() {
        let station = |commanded_rad, via_rad| TableStation {
            station: "c".into(),
            commanded_rad,
            via_rad,
            from_ns: 0,
            until_ns: 0,
        };
        let on_table = [
            station(0.0, None),
            station(0.5, None),
            station(0.5, Some(0.6)),
            station(0.3, None),
            station(0.3, None),
            station(0.3, Some(0.25)),
        ];
        let got: Vec<Option<i8>> = (0..on_table.len())
            .map(|k| approach(&on_table, k))
            .collect();
        assert_eq!(got, [None, Some(1), Some(-1), Some(-1), None, Some(1)]);
    }

    #[test]
    fn wrap_pi_keeps_the_half_open_interval() {
        assert!((wrap_pi(3.0 * std::f64::consts::PI) - std::f64::consts::PI).abs() < 1e-12);
        assert!((wrap_pi(-0.1) + 0.1).abs() < 1e-15);
        assert!((wrap_pi(std::f64::consts::TAU + 0.2) - 0.2).abs() < 1e-12);
    }
}
