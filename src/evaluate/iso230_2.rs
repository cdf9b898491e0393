//! ISO 230-2:2014 positioning figures of one axis (linear in metres, rotary in radians) from
//! the deviations of every run and direction at every target, and the test-cycle conformance.

use serde::{Deserialize, Serialize};

/// The figures of every axis a kind's results measured (`super::deviations`).
pub use super::deviations::of_results;

/// Runs per direction the standard's test cycle asks for.
pub const MIN_RUNS: usize = 5;
/// Target positions: at least this many overall, and this many per metre of linear travel.
pub const MIN_TARGETS: usize = 5;
/// Target positions per full turn of a rotary axis.
pub const MIN_TARGETS_ROTARY_TURN: usize = 8;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AxisType {
    /// Positions and deviations in metres.
    Linear,
    /// Positions and deviations in radians.
    Rotary,
}

/// The measured deviations of one axis: `up[j][i]` is x_ij↑ = P_ij − P_i of run j at target i
/// (actual minus target), `down[j][i]` the same for ↓ approaches.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Curves {
    pub axis_type: AxisType,
    /// Target positions P_i, strictly increasing (m or rad).
    pub targets: Vec<f64>,
    pub up: Vec<Vec<f64>>,
    pub down: Vec<Vec<f64>>,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CurvesError {
    #[error("ISO 230-2: {0} target positions, at least 2 are needed")]
    TooFewTargets(usize),
    #[error("ISO 230-2: target {index} is {value}, expected a finite position larger than the one before ({previous})")]
    TargetsNotIncreasing {
        index: usize,
        value: f64,
        previous: f64,
    },
    #[error("ISO 230-2: no run in either direction")]
    NoRuns,
    #[error("ISO 230-2: run {run} {direction} has {got} deviations, expected one per target ({expected})")]
    RunLength {
        run: usize,
        direction: &'static str,
        got: usize,
        expected: usize,
    },
    #[error("ISO 230-2: deviation of run {run} {direction} at target {target} is {value}, expected a finite number")]
    NotFinite {
        run: usize,
        direction: &'static str,
        target: usize,
        value: f64,
    },
}

/// Figures of one approach direction (↑ or ↓), in the unit of the enclosing block.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Unidirectional {
    /// n, the number of runs in this direction.
    pub runs: usize,
    /// x̄_i↑ (or ↓): mean positional deviation at each target.
    pub mean_deviation_i: Vec<f64>,
    /// s_i↑: estimator of the standard uncertainty at each target (None with one run).
    pub s_i: Vec<Option<f64>>,
    /// R_i↑ = 4 s_i↑.
    pub repeatability_i: Vec<Option<f64>>,
    /// R↑ = max R_i↑.
    pub repeatability: Option<f64>,
    /// E↑ = max x̄_i↑ − min x̄_i↑.
    pub systematic_error: f64,
    /// A↑ = max(x̄_i↑ + 2 s_i↑) − min(x̄_i↑ − 2 s_i↑).
    pub accuracy: Option<f64>,
}

/// Figures that need both directions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Bidirectional {
    /// x̄_i = (x̄_i↑ + x̄_i↓) / 2.
    pub mean_deviation_i: Vec<f64>,
    /// B_i = x̄_i↑ − x̄_i↓.
    pub reversal_i: Vec<f64>,
    /// B = max |B_i|.
    pub reversal: f64,
    /// B̄ = mean of B_i.
    pub mean_reversal: f64,
    /// R_i = max(2 s_i↑ + 2 s_i↓ + |B_i|, R_i↑, R_i↓).
    pub repeatability_i: Vec<Option<f64>>,
    /// R = max R_i.
    pub repeatability: Option<f64>,
    /// E = max(x̄_i↑, x̄_i↓) − min(x̄_i↑, x̄_i↓).
    pub systematic_error: f64,
    /// M = max x̄_i − min x̄_i.
    pub mean_error: f64,
    /// A = max(x̄_i↑ + 2 s_i↑, x̄_i↓ + 2 s_i↓) − min(x̄_i↑ − 2 s_i↑, x̄_i↓ − 2 s_i↓).
    pub accuracy: Option<f64>,
}

/// Every figure of one axis, all in one unit (the key of the block says which).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Figures {
    /// P_i.
    pub targets: Vec<f64>,
    pub up: Option<Unidirectional>,
    pub down: Option<Unidirectional>,
    pub bidirectional: Option<Bidirectional>,
}

/// The figures in the axis's SI unit: `figures_m` for a linear axis, `figures_rad` for a
/// rotary one.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum UnitFigures {
    #[serde(rename = "figures_m")]
    Metres(Figures),
    #[serde(rename = "figures_rad")]
    Radians(Figures),
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Evaluation {
    pub axis_type: AxisType,
    /// m, the number of target positions.
    pub targets: usize,
    pub runs_up: usize,
    pub runs_down: usize,
    /// Empty when the measurement follows the standard's test cycle; otherwise why not
    /// (the figures are computed anyway).
    pub not_per_iso_230_2: Vec<String>,
    #[serde(flatten)]
    pub figures: UnitFigures,
}

impl Evaluation {
    pub fn figures(&self) -> &Figures {
        match &self.figures {
            UnitFigures::Metres(f) | UnitFigures::Radians(f) => f,
        }
    }

    /// "per ISO 230-2" or "not per ISO 230-2: <why>; <why>".
    pub fn verdict(&self) -> String {
        if self.not_per_iso_230_2.is_empty() {
            "per ISO 230-2".to_owned()
        } else {
            format!("not per ISO 230-2: {}", self.not_per_iso_230_2.join("; "))
        }
    }

    /// A short table: µm for a linear axis, arcsec for a rotary one.
    pub fn text(&self, axis: &str) -> String {
        let (scale, unit) = match self.axis_type {
            AxisType::Linear => (1e6, "µm"),
            AxisType::Rotary => (180.0 / std::f64::consts::PI * 3600.0, "\""),
        };
        let f = self.figures();
        let v = |x: Option<f64>| match x {
            Some(x) => format!("{:.3}", x * scale),
            None => "-".to_owned(),
        };
        let mut out = format!(
            "ISO 230-2, axis {axis}: {} targets, runs ↑ {} ↓ {} — {}\n",
            self.targets,
            self.runs_up,
            self.runs_down,
            self.verdict()
        );
        for (name, d) in [("↑", &f.up), ("↓", &f.down)] {
            if let Some(d) = d {
                out += &format!(
                    "  {name}  E {} {unit}  R {} {unit}  A {} {unit}\n",
                    v(Some(d.systematic_error)),
                    v(d.repeatability),
                    v(d.accuracy)
                );
            }
        }
        if let Some(b) = &f.bidirectional {
            out += &format!(
                "  ↕  E {} {unit}  R {} {unit}  A {} {unit}  M {} {unit}  B {} {unit}  B̄ {} {unit}\n",
                v(Some(b.systematic_error)),
                v(b.repeatability),
                v(b.accuracy),
                v(Some(b.mean_error)),
                v(Some(b.reversal)),
                v(Some(b.mean_reversal))
            );
        }
        out
    }
}

/// Check the curves and compute every figure and the conformance of the test cycle.
pub fn evaluate(curves: &Curves) -> Result<Evaluation, CurvesError> {
    validate(curves)?;
    let up = unidirectional(&curves.up);
    let down = unidirectional(&curves.down);
    let bidirectional = match (&up, &down) {
        (Some(u), Some(d)) => Some(bidirectional(u, d)),
        _ => None,
    };
    let figures = Figures {
        targets: curves.targets.clone(),
        up,
        down,
        bidirectional,
    };
    Ok(Evaluation {
        axis_type: curves.axis_type,
        targets: curves.targets.len(),
        runs_up: curves.up.len(),
        runs_down: curves.down.len(),
        not_per_iso_230_2: conformance(curves),
        figures: match curves.axis_type {
            AxisType::Linear => UnitFigures::Metres(figures),
            AxisType::Rotary => UnitFigures::Radians(figures),
        },
    })
}

fn validate(curves: &Curves) -> Result<(), CurvesError> {
    let m = curves.targets.len();
    if m < 2 {
        return Err(CurvesError::TooFewTargets(m));
    }
    for (index, pair) in curves.targets.windows(2).enumerate() {
        if !pair[1].is_finite() || !pair[0].is_finite() || pair[1] <= pair[0] {
            return Err(CurvesError::TargetsNotIncreasing {
                index: index + 1,
                value: pair[1],
                previous: pair[0],
            });
        }
    }
    if curves.up.is_empty() && curves.down.is_empty() {
        return Err(CurvesError::NoRuns);
    }
    for (direction, runs) in [("↑", &curves.up), ("↓", &curves.down)] {
        for (run, values) in runs.iter().enumerate() {
            if values.len() != m {
                return Err(CurvesError::RunLength {
                    run,
                    direction,
                    got: values.len(),
                    expected: m,
                });
            }
            if let Some((target, &value)) = values.iter().enumerate().find(|(_, v)| !v.is_finite())
            {
                return Err(CurvesError::NotFinite {
                    run,
                    direction,
                    target,
                    value,
                });
            }
        }
    }
    Ok(())
}

fn max(values: impl IntoIterator<Item = f64>) -> f64 {
    values.into_iter().fold(f64::NEG_INFINITY, f64::max)
}

fn min(values: impl IntoIterator<Item = f64>) -> f64 {
    values.into_iter().fold(f64::INFINITY, f64::min)
}

/// Every element, or None when any is None.
fn all<T: Copy>(values: &[Option<T>]) -> Option<Vec<T>> {
    values.iter().copied().collect()
}

fn unidirectional(runs: &[Vec<f64>]) -> Option<Unidirectional> {
    let n = runs.len();
    let m = runs.first()?.len();
    let mean: Vec<f64> = (0..m)
        .map(|i| runs.iter().map(|r| r[i]).sum::<f64>() / n as f64)
        .collect();
    let s: Vec<Option<f64>> = (0..m)
        .map(|i| {
            (n >= 2).then(|| {
                let ss: f64 = runs.iter().map(|r| (r[i] - mean[i]).powi(2)).sum();
                (ss / (n - 1) as f64).sqrt()
            })
        })
        .collect();
    let repeatability_i: Vec<Option<f64>> = s.iter().map(|s| s.map(|s| 4.0 * s)).collect();
    let repeatability = all(&repeatability_i).map(max);
    let accuracy = all(&s).map(|s| {
        max(mean.iter().zip(&s).map(|(x, s)| x + 2.0 * s))
            - min(mean.iter().zip(&s).map(|(x, s)| x - 2.0 * s))
    });
    Some(Unidirectional {
        runs: n,
        systematic_error: max(mean.iter().copied()) - min(mean.iter().copied()),
        mean_deviation_i: mean,
        s_i: s,
        repeatability_i,
        repeatability,
        accuracy,
    })
}

fn bidirectional(up: &Unidirectional, down: &Unidirectional) -> Bidirectional {
    let (xu, xd) = (&up.mean_deviation_i, &down.mean_deviation_i);
    let m = xu.len();
    let mean: Vec<f64> = (0..m).map(|i| 0.5 * (xu[i] + xd[i])).collect();
    let reversal_i: Vec<f64> = (0..m).map(|i| xu[i] - xd[i]).collect();
    let repeatability_i: Vec<Option<f64>> = (0..m)
        .map(|i| match (up.s_i[i], down.s_i[i]) {
            (Some(su), Some(sd)) => Some(
                (2.0 * su + 2.0 * sd + reversal_i[i].abs())
                    .max(4.0 * su)
                    .max(4.0 * sd),
            ),
            _ => None,
        })
        .collect();
    let accuracy = match (all(&up.s_i), all(&down.s_i)) {
        (Some(su), Some(sd)) => {
            let high = (0..m).flat_map(|i| [xu[i] + 2.0 * su[i], xd[i] + 2.0 * sd[i]]);
            let low = (0..m).flat_map(|i| [xu[i] - 2.0 * su[i], xd[i] - 2.0 * sd[i]]);
            Some(max(high) - min(low))
        }
        _ => None,
    };
    Bidirectional {
        reversal: max(reversal_i.iter().map(|b| b.abs())),
        mean_reversal: reversal_i.iter().sum::<f64>() / m as f64,
        repeatability: all(&repeatability_i).map(max),
        systematic_error: max(xu.iter().chain(xd).copied()) - min(xu.iter().chain(xd).copied()),
        mean_error: max(mean.iter().copied()) - min(mean.iter().copied()),
        mean_deviation_i: mean,
        reversal_i,
        repeatability_i,
        accuracy,
    }
}

/// Why the measurement does not follow the standard's test cycle (empty when it does).
pub fn conformance(curves: &Curves) -> Vec<String> {
    let mut why = Vec::new();
    match (curves.up.is_empty(), curves.down.is_empty()) {
        (false, true) => why.push("unidirectional only (no ↓ runs)".to_owned()),
        (true, false) => why.push("unidirectional only (no ↑ runs)".to_owned()),
        _ => {}
    }
    for (name, runs) in [("↑", &curves.up), ("↓", &curves.down)] {
        if !runs.is_empty() && runs.len() < MIN_RUNS {
            why.push(format!(
                "{} runs {name}, at least {MIN_RUNS} per direction",
                runs.len()
            ));
        }
    }
    let m = curves.targets.len();
    let (Some(&first), Some(&last)) = (curves.targets.first(), curves.targets.last()) else {
        return why;
    };
    let span = last - first;
    match curves.axis_type {
        AxisType::Linear => {
            let per_metre = (MIN_TARGETS as f64 * span - 1e-9).ceil().max(0.0) as usize;
            let needed = per_metre.max(MIN_TARGETS);
            if m < needed {
                why.push(format!(
                    "{m} target positions over {span:.3} m, at least {needed} ({MIN_TARGETS} per metre, {MIN_TARGETS} overall)"
                ));
            }
        }
        AxisType::Rotary => {
            let turns = span / std::f64::consts::TAU;
            let needed =
                ((MIN_TARGETS_ROTARY_TURN as f64 * turns - 1e-9).ceil() as usize).max(MIN_TARGETS);
            if m < needed {
                why.push(format!(
                    "{m} target positions over {:.1}°, at least {needed} ({MIN_TARGETS_ROTARY_TURN} per turn)",
                    span.to_degrees()
                ));
            }
        }
    }
    if m >= 3 {
        let intervals: Vec<f64> = curves.targets.windows(2).map(|p| p[1] - p[0]).collect();
        let mean = span / (m - 1) as f64;
        if intervals
            .iter()
            .all(|d| (d - mean).abs() <= 1e-9 * span.abs().max(1.0))
        {
            why.push(
                "targets equally spaced (the standard asks for unequal intervals so that periodic errors are sampled)"
                    .to_owned(),
            );
        }
        if let Some((k, d)) = intervals
            .iter()
            .enumerate()
            .find(|(_, &d)| d > 2.0 * mean + 1e-12)
        {
            why.push(format!(
                "targets not spread over the travel: interval {k}–{} is {d:.6}, more than twice the mean interval {mean:.6}",
                k + 1
            ));
        }
    }
    why
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 3 targets, 2 runs per direction, deviations in µm (scaled to m below).
    ///
    /// ↑ runs: [1, 3, 2], [3, 5, 2]      ↓ runs: [-1, 1, 0], [-1, 3, 2]
    /// x̄↑ = [2, 4, 2]; s↑: target 0 {1,3} → sqrt((1+1)/1) = √2, target 1 {3,5} → √2,
    ///   target 2 {2,2} → 0.
    /// x̄↓ = [-1, 2, 1]; s↓: {-1,-1} → 0, {1,3} → √2, {0,2} → √2.
    /// B_i = x̄↑ − x̄↓ = [3, 2, 1]; B = 3; B̄ = 2.
    /// x̄_i = [0.5, 3, 1.5]; M = 3 − 0.5 = 2.5.
    /// E↑ = 4 − 2 = 2; E↓ = 2 − (−1) = 3; E = max(2,4,2,−1,2,1) − min(...) = 4 − (−1) = 5.
    /// R_i↑ = 4√2, 4√2, 0 → R↑ = 4√2; R_i↓ = 0, 4√2, 4√2 → R↓ = 4√2.
    /// R_i = max(2s↑ + 2s↓ + |B_i|, R_i↑, R_i↓):
    ///   target 0: 2√2 + 0 + 3 = 5.828 vs 4√2 = 5.657 → 2√2 + 3
    ///   target 1: 2√2 + 2√2 + 2 = 7.657 → 4√2 + 2
    ///   target 2: 0 + 2√2 + 1 = 3.828 vs 4√2 → 4√2
    ///   R = 4√2 + 2.
    /// A↑: highs [2 + 2√2, 4 + 2√2, 2], lows [2 − 2√2, 4 − 2√2, 2] → 4 + 2√2 − (2 − 2√2) = 2 + 4√2.
    /// A↓: highs [-1, 2 + 2√2, 1 + 2√2], lows [-1, 2 − 2√2, 1 − 2√2]
    ///   → 2 + 2√2 − (1 − 2√2) = 1 + 4√2.
    /// A: max high 4 + 2√2, min low 1 − 2√2 → 3 + 4√2.
    #[test]
    fn hand_computed_example() {
        let um = 1e-6;
        let scale = |rows: &[[f64; 3]]| -> Vec<Vec<f64>> {
            rows.iter()
                .map(|r| r.iter().map(|v| v * um).collect())
                .collect()
        };
        let curves = Curves {
            axis_type: AxisType::Linear,
            targets: vec![0.0, 0.13, 0.31],
            up: scale(&[[1.0, 3.0, 2.0], [3.0, 5.0, 2.0]]),
            down: scale(&[[-1.0, 1.0, 0.0], [-1.0, 3.0, 2.0]]),
        };
        let e = evaluate(&curves).unwrap();
        let f = e.figures();
        let r2 = 2f64.sqrt();
        let close = |got: f64, want_um: f64, what: &str| {
            assert!(
                (got - want_um * um).abs() < 1e-15,
                "{what}: got {} µm, expected {want_um} µm",
                got / um
            )
        };
        let up = f.up.as_ref().unwrap();
        let down = f.down.as_ref().unwrap();
        let b = f.bidirectional.as_ref().unwrap();
        close(up.systematic_error, 2.0, "E↑");
        close(down.systematic_error, 3.0, "E↓");
        close(b.systematic_error, 5.0, "E");
        close(b.reversal, 3.0, "B");
        close(b.mean_reversal, 2.0, "B̄");
        close(b.mean_error, 2.5, "M");
        close(up.repeatability.unwrap(), 4.0 * r2, "R↑");
        close(down.repeatability.unwrap(), 4.0 * r2, "R↓");
        close(b.repeatability.unwrap(), 4.0 * r2 + 2.0, "R");
        close(b.repeatability_i[0].unwrap(), 2.0 * r2 + 3.0, "R_0");
        close(b.repeatability_i[2].unwrap(), 4.0 * r2, "R_2");
        close(up.accuracy.unwrap(), 2.0 + 4.0 * r2, "A↑");
        close(down.accuracy.unwrap(), 1.0 + 4.0 * r2, "A↓");
        close(b.accuracy.unwrap(), 3.0 + 4.0 * r2, "A");
        assert_eq!((e.runs_up, e.runs_down, e.targets), (2, 2, 3));
        // 2 runs, 3 targets over 0.31 m: both rules broken, and the verdict says so.
        assert!(
            e.verdict().starts_with("not per ISO 230-2: "),
            "{}",
            e.verdict()
        );
        assert!(e.not_per_iso_230_2.iter().any(|w| w.contains("2 runs ↑")));
        assert!(e
            .not_per_iso_230_2
            .iter()
            .any(|w| w.contains("3 target positions")));
        let json = serde_json::to_value(&e).unwrap();
        assert!(json["figures_m"]["bidirectional"]["reversal"].is_number());
    }

    fn cycle(targets: Vec<f64>, runs: usize, axis_type: AxisType) -> Curves {
        let m = targets.len();
        Curves {
            axis_type,
            targets,
            up: vec![vec![0.0; m]; runs],
            down: vec![vec![0.0; m]; runs],
        }
    }

    #[test]
    fn standard_cycle_conforms_and_each_shortfall_is_named() {
        let spread = vec![0.0, 0.093, 0.21, 0.288, 0.41, 0.507, 0.6];
        assert_eq!(
            conformance(&cycle(spread.clone(), 5, AxisType::Linear)),
            Vec::<String>::new()
        );
        let short = conformance(&cycle(spread.clone(), 4, AxisType::Linear));
        assert!(short.iter().any(|w| w.contains("4 runs ↑")), "{short:?}");
        let mut one_way = cycle(spread, 5, AxisType::Linear);
        one_way.down.clear();
        let why = conformance(&one_way);
        assert!(why.iter().any(|w| w.contains("unidirectional")), "{why:?}");
        // 7 targets over 1.8 m: 9 are needed.
        let long = vec![0.0, 0.31, 0.58, 0.92, 1.2, 1.49, 1.8];
        let why = conformance(&cycle(long, 5, AxisType::Linear));
        assert!(why.iter().any(|w| w.contains("at least 9")), "{why:?}");
        let equal: Vec<f64> = (0..6).map(|i| 0.1 * i as f64).collect();
        let why = conformance(&cycle(equal, 5, AxisType::Linear));
        assert!(why.iter().any(|w| w.contains("equally spaced")), "{why:?}");
        let bunched = vec![0.0, 0.01, 0.02, 0.03, 0.6];
        let why = conformance(&cycle(bunched, 5, AxisType::Linear));
        assert!(why.iter().any(|w| w.contains("not spread")), "{why:?}");
        let turn: Vec<f64> = (0..12)
            .map(|k| (k as f64 * 30.0 + 1.3 * (k % 3) as f64).to_radians())
            .collect();
        let rotary = cycle(turn, 5, AxisType::Rotary);
        assert_eq!(conformance(&rotary), Vec::<String>::new());
        let e = evaluate(&rotary).unwrap();
        assert!(serde_json::to_value(&e).unwrap()["figures_rad"].is_object());
    }

    #[test]
    fn one_run_gives_means_but_no_repeatability() {
        let curves = Curves {
            axis_type: AxisType::Linear,
            targets: vec![0.0, 0.1, 0.25],
            up: vec![vec![1e-6, 2e-6, 0.0]],
            down: vec![],
        };
        let e = evaluate(&curves).unwrap();
        let up = e.figures().up.as_ref().unwrap();
        assert_eq!(up.repeatability, None);
        assert_eq!(up.accuracy, None);
        assert!((up.systematic_error - 2e-6).abs() < 1e-18);
        assert!(e.figures().bidirectional.is_none());
    }

    #[test]
    fn bad_curves_are_named() {
        let mut c = cycle(vec![0.0, 0.1, 0.2], 2, AxisType::Linear);
        c.down[1].pop();
        let err = evaluate(&c).unwrap_err().to_string();
        assert!(
            err.contains("run 1 ↓ has 2 deviations") && err.contains("(3)"),
            "{err}"
        );
        let mut c = cycle(vec![0.0, 0.1, 0.2], 2, AxisType::Linear);
        c.up[0][2] = f64::NAN;
        let err = evaluate(&c).unwrap_err().to_string();
        assert!(err.contains("run 0 ↑ at target 2"), "{err}");
        let c = cycle(vec![0.0, 0.2, 0.1], 2, AxisType::Linear);
        assert!(evaluate(&c)
            .unwrap_err()
            .to_string()
            .contains("target 2 is 0.1"));
        let c = Curves {
            axis_type: AxisType::Linear,
            targets: vec![0.0, 0.1],
            up: vec![],
            down: vec![],
        };
        assert_eq!(evaluate(&c).unwrap_err(), CurvesError::NoRuns);
    }
}
