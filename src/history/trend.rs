//! `geocal trend`: a machine's parameters over a series of its runs, each with ±2σ, a
//! tolerance band (user-set, or from the first runs), and the events found: a step (the level
//! after a run differs from the level before beyond the combined uncertainty), a drift (a
//! weighted slope significantly non-zero), a value outside the tolerance band. JSON
//! (geocal-trend/1) and an HTML report with SVG plots.

use serde::Serialize;

use super::compare::{check_comparable, check_positions, display, short, RunRef, Tolerances};
use super::load::{MachineIdentity, Run};
use super::parameters::{parameters, Parameter, Parameters};
use super::stats::{best_step, holm, two_sided_p, two_sided_quantile, weighted_line};

/// The JSON format of a trend.
pub const TREND_FORMAT: &str = "geocal-trend/1";

const SECONDS_PER_DAY: f64 = 86_400.0;

/// The choices of a trend.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TrendOptions {
    /// Family-wise false-alarm probability of the whole series (every parameter, every test).
    pub alpha: f64,
    /// Allowed departure of each parameter from its baseline (the mean of the first runs);
    /// for a unit without one, the band comes from the first runs' scatter.
    pub tolerances: Tolerances,
    /// How many of the first runs make the baseline.
    pub baseline_runs: usize,
}

impl Default for TrendOptions {
    fn default() -> Self {
        TrendOptions {
            alpha: 0.05,
            tolerances: Tolerances::default(),
            baseline_runs: 5,
        }
    }
}

/// A run in the series, with its time in days since the first run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrendRun {
    #[serde(flatten)]
    pub run: RunRef,
    pub t_days: f64,
}

/// The tolerance band of a parameter: centre ± half width.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Band {
    pub centre: f64,
    pub half_width: f64,
    /// `tolerance` (user-set) or `baseline` (from the first runs' scatter).
    pub source: String,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DriftFit {
    /// Units per day.
    pub rate_per_day: f64,
    pub sigma_per_day: f64,
    pub z: f64,
    pub p: f64,
    pub p_adjusted: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StepFit {
    /// Index (in `runs`) of the first run at the new level.
    pub at_run: usize,
    pub size: f64,
    pub sigma: f64,
    pub z: f64,
    /// p of the largest |z| over every split of the series (Bonferroni over the splits).
    pub p: f64,
    pub p_adjusted: f64,
}

/// One parameter over the series (null where a run did not estimate it).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ParameterTrend {
    /// Its name (docs/history.md, "Which parameters").
    pub id: String,
    /// Its JSON path in the results.
    pub path: String,
    pub curve: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub x: Option<f64>,
    #[serde(skip_serializing_if = "String::is_empty")]
    pub x_unit: String,
    pub unit: String,
    pub values: Vec<Option<f64>>,
    pub sigmas: Vec<Option<f64>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub band: Option<Band>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub drift: Option<DriftFit>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub step: Option<StepFit>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum EventKind {
    Step,
    Drift,
    OutsideTolerance,
}

/// Something found in the series.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Event {
    pub kind: EventKind,
    pub parameter: String,
    /// The run it is found at (a step: the first run at the new level; outside tolerance:
    /// the run outside; a drift: the last run).
    pub run: usize,
    pub run_label: String,
    pub unit: String,
    /// Step: its size; outside tolerance: the departure from the band's centre.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub size: Option<f64>,
    /// Drift: units per day.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rate_per_day: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sigma: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub z: Option<f64>,
    pub message: String,
}

/// geocal-trend/1.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Trend {
    pub format: String,
    pub kind: String,
    pub machine: MachineIdentity,
    pub runs: Vec<TrendRun>,
    pub alpha: f64,
    pub correction: String,
    pub tolerances: Tolerances,
    pub baseline_runs: usize,
    /// Step and drift tests in the Holm family.
    pub tests: usize,
    pub events: Vec<Event>,
    pub notes: Vec<String>,
    pub parameters: Vec<ParameterTrend>,
}

impl TrendOptions {
    pub fn check(&self) -> anyhow::Result<()> {
        if !(self.alpha > 0.0 && self.alpha < 1.0) {
            anyhow::bail!(
                "significance level: expected a number between 0 and 1, found {}",
                self.alpha
            );
        }
        if self.baseline_runs < 2 {
            anyhow::bail!(
                "baseline runs: expected at least 2, found {}",
                self.baseline_runs
            );
        }
        self.tolerances.check()
    }
}

/// The trend of a series of runs of one machine, oldest first.
pub fn trend(runs: &[Run], options: &TrendOptions) -> anyhow::Result<Trend> {
    options.check()?;
    let Some(first) = runs.first() else {
        anyhow::bail!("no runs to trend");
    };
    if runs.len() < 2 {
        anyhow::bail!("{}: a trend needs at least 2 runs, found 1", first.label);
    }
    let mut notes = Vec::new();
    for run in &runs[1..] {
        for note in check_comparable(first, run)? {
            if !notes.contains(&note) {
                notes.push(note);
            }
        }
    }
    let t_days: Vec<f64> = match runs
        .iter()
        .map(|r| r.started_at)
        .collect::<Option<Vec<_>>>()
    {
        Some(times) => times
            .iter()
            .map(|t| (*t - times[0]).num_milliseconds() as f64 / 1e3 / SECONDS_PER_DAY)
            .collect(),
        None => {
            notes.push("a run has no start time: runs are spaced one day apart".into());
            (0..runs.len()).map(|i| i as f64).collect()
        }
    };
    let per_run: Vec<Parameters> = runs.iter().map(|r| parameters(&r.results)).collect();
    // Every parameter any run estimates, in the order of the first run that has it.
    let mut order: Vec<&Parameter> = Vec::new();
    for (run, params) in runs.iter().zip(&per_run) {
        for p in &params.parameters {
            // Matched by path: a parameter at another position is an incompatible plan.
            match order.iter().find(|q| q.path == p.path) {
                Some(q) => check_positions(first, q, run, p)?,
                None => order.push(p),
            }
        }
    }
    let mut trends: Vec<ParameterTrend> = order
        .iter()
        .map(|p| {
            let (values, sigmas) = per_run
                .iter()
                .map(|params| match params.at_path(&p.path) {
                    Some(q) => (Some(q.value), Some(q.sigma)),
                    None => (None, None),
                })
                .unzip();
            ParameterTrend {
                id: p.id.clone(),
                path: p.path.clone(),
                curve: p.curve.clone(),
                x: p.x,
                x_unit: p.x_unit.clone(),
                unit: p.unit.clone(),
                values,
                sigmas,
                band: None,
                drift: None,
                step: None,
            }
        })
        .collect();

    // The tolerance band: user tolerances around the baseline; else the baseline's scatter.
    let baseline = options.baseline_runs.min(runs.len());
    let data_driven = |unit: &str| options.tolerances.of(unit).is_none();
    let any_data_driven = trends.iter().any(|t| data_driven(&t.unit));
    let enough_for_baseline = runs.len() > options.baseline_runs;
    // Without user tolerances, half of α goes to the band and half to the step/drift tests.
    let alpha_tests = if any_data_driven && enough_for_baseline {
        options.alpha / 2.0
    } else {
        options.alpha
    };
    if any_data_driven && !enough_for_baseline {
        notes.push(format!(
            "{} runs: a band from the first runs' scatter needs more than the {} baseline \
             runs (set tolerances, or --baseline-runs)",
            runs.len(),
            options.baseline_runs
        ));
    }
    let banded_checks: usize = trends
        .iter()
        .filter(|t| data_driven(&t.unit) && enough_for_baseline)
        .map(|t| t.values[baseline..].iter().flatten().count())
        .sum();
    for t in &mut trends {
        let base: Vec<(f64, f64)> = t.values[..baseline]
            .iter()
            .zip(&t.sigmas[..baseline])
            .filter_map(|(v, s)| Some(((*v)?, (*s)?)))
            .collect();
        if base.len() < 2 {
            continue;
        }
        let n = base.len() as f64;
        let centre = base.iter().map(|(v, _)| v).sum::<f64>() / n;
        t.band = match options.tolerances.of(&t.unit) {
            Some(tolerance) => Some(Band {
                centre,
                half_width: tolerance,
                source: "tolerance".into(),
            }),
            None if enough_for_baseline && banded_checks > 0 => {
                // A prediction interval for one later run: the baseline's scatter, never
                // below what the runs' own σ say, Bonferroni over every check of the series.
                let scatter =
                    base.iter().map(|(v, _)| (v - centre).powi(2)).sum::<f64>() / (n - 1.0);
                let noise = base.iter().map(|(_, s)| s * s).sum::<f64>() / n;
                let spread = (scatter.max(noise) * (1.0 + 1.0 / n)).sqrt();
                let q = two_sided_quantile(options.alpha / 2.0 / banded_checks as f64);
                Some(Band {
                    centre,
                    half_width: q * spread,
                    source: "baseline".into(),
                })
            }
            None => None,
        };
    }

    // Step and drift of every parameter, one Holm family.
    for t in &mut trends {
        let present: Vec<(usize, f64, f64)> = t
            .values
            .iter()
            .zip(&t.sigmas)
            .enumerate()
            .filter_map(|(i, (v, s))| Some((i, (*v)?, (*s)?)))
            .collect();
        let times: Vec<f64> = present.iter().map(|(i, _, _)| t_days[*i]).collect();
        let y: Vec<f64> = present.iter().map(|(_, v, _)| *v).collect();
        let s: Vec<f64> = present.iter().map(|(_, _, s)| *s).collect();
        if let Some(line) = weighted_line(&times, &y, &s) {
            let z = line.slope / line.slope_sigma;
            t.drift = Some(DriftFit {
                rate_per_day: line.slope,
                sigma_per_day: line.slope_sigma,
                z,
                p: two_sided_p(z),
                p_adjusted: 1.0,
            });
        }
        if let Some(step) = best_step(&y, &s) {
            let splits = (y.len() - 1) as f64;
            t.step = Some(StepFit {
                at_run: present[step.at].0,
                size: step.size,
                sigma: step.sigma,
                z: step.z,
                p: (splits * two_sided_p(step.z)).min(1.0),
                p_adjusted: 1.0,
            });
        }
    }
    let mut family: Vec<f64> = Vec::new();
    for t in &trends {
        family.extend(t.drift.as_ref().map(|d| d.p));
        family.extend(t.step.as_ref().map(|s| s.p));
    }
    let adjusted = holm(&family);
    let mut next = adjusted.into_iter();
    for t in &mut trends {
        if let Some(d) = &mut t.drift {
            d.p_adjusted = next.next().unwrap_or(1.0);
        }
        if let Some(s) = &mut t.step {
            s.p_adjusted = next.next().unwrap_or(1.0);
        }
    }

    let label = |i: usize| runs[i].label.clone();
    let mut events = Vec::new();
    for t in &trends {
        let name = short(&t.id);
        let unit_value = |v: f64| display(v, &t.unit);
        let drift = t.drift.as_ref().filter(|d| d.p_adjusted <= alpha_tests);
        let step = t.step.as_ref().filter(|s| s.p_adjusted <= alpha_tests);
        // A step also tilts a line and a drift also splits into levels: keep the model that
        // fits the series better.
        let keep_step = match (step, drift) {
            (Some(_), Some(_)) => step_fits_better(t, &t_days),
            (Some(_), None) => true,
            _ => false,
        };
        if let (true, Some(s)) = (keep_step, step) {
            let (size, u) = unit_value(s.size);
            events.push(Event {
                kind: EventKind::Step,
                parameter: t.id.clone(),
                run: s.at_run,
                run_label: label(s.at_run),
                unit: t.unit.clone(),
                size: Some(s.size),
                rate_per_day: None,
                sigma: Some(s.sigma),
                z: Some(s.z),
                message: format!(
                    "{name}: a step of {size:.3} {u} (z {:.1}) from run {} ({})",
                    s.z,
                    s.at_run + 1,
                    label(s.at_run)
                ),
            });
        } else if let Some(d) = drift {
            let last = t.values.iter().rposition(Option::is_some).unwrap_or(0);
            let (rate, u) = unit_value(d.rate_per_day);
            let (rate_sigma, _) = unit_value(d.sigma_per_day);
            events.push(Event {
                kind: EventKind::Drift,
                parameter: t.id.clone(),
                run: last,
                run_label: label(last),
                unit: t.unit.clone(),
                size: None,
                rate_per_day: Some(d.rate_per_day),
                sigma: Some(d.sigma_per_day),
                z: Some(d.z),
                message: format!(
                    "{name}: drifts {rate:.4} ± {rate_sigma:.4} {u}/day (z {:.1})",
                    d.z
                ),
            });
        }
        if let Some(band) = &t.band {
            let from = if band.source == "baseline" {
                baseline
            } else {
                0
            };
            for (i, v) in t.values.iter().enumerate().skip(from) {
                let Some(v) = v else { continue };
                let departure = v - band.centre;
                if departure.abs() > band.half_width {
                    let (d, u) = unit_value(departure);
                    let (w, _) = unit_value(band.half_width);
                    events.push(Event {
                        kind: EventKind::OutsideTolerance,
                        parameter: t.id.clone(),
                        run: i,
                        run_label: label(i),
                        unit: t.unit.clone(),
                        size: Some(departure),
                        rate_per_day: None,
                        sigma: t.sigmas[i],
                        z: None,
                        message: format!(
                            "{name}: run {} ({}) lies {d:.3} {u} from the baseline, beyond \
                             the {} band of ±{w:.3} {u}",
                            i + 1,
                            label(i),
                            band.source
                        ),
                    });
                }
            }
        }
    }
    events.sort_by_key(|e| e.run);
    Ok(Trend {
        format: TREND_FORMAT.into(),
        kind: first.kind.clone(),
        machine: runs
            .iter()
            .map(|r| r.machine.clone())
            .find(MachineIdentity::is_known)
            .unwrap_or_default(),
        runs: runs
            .iter()
            .zip(&t_days)
            .map(|(r, t)| TrendRun {
                run: RunRef::of(r),
                t_days: *t,
            })
            .collect(),
        alpha: options.alpha,
        correction: format!(
            "holm-bonferroni over the step and drift tests at {alpha_tests}; a band from the \
             baseline is a prediction interval, Bonferroni over its checks at {}",
            options.alpha - alpha_tests
        ),
        tolerances: options.tolerances,
        baseline_runs: baseline,
        tests: family.len(),
        events,
        notes,
        parameters: trends,
    })
}

/// Whether the best step explains the series better (smaller weighted residual) than the line.
fn step_fits_better(t: &ParameterTrend, t_days: &[f64]) -> bool {
    let present: Vec<(f64, f64, f64)> = t
        .values
        .iter()
        .zip(&t.sigmas)
        .zip(t_days)
        .filter_map(|((v, s), time)| Some((*time, (*v)?, (*s)?)))
        .collect();
    let times: Vec<f64> = present.iter().map(|p| p.0).collect();
    let y: Vec<f64> = present.iter().map(|p| p.1).collect();
    let s: Vec<f64> = present.iter().map(|p| p.2).collect();
    match (best_step(&y, &s), weighted_line(&times, &y, &s)) {
        (Some(step), Some(line)) => step.chi2 < line.chi2,
        (Some(_), None) => true,
        _ => false,
    }
}

/// The trend as people read it.
pub fn text(t: &Trend) -> String {
    let mut out = format!(
        "Trend of {} over {} {} runs ({} to {})\n  {} parameters, {} step and drift tests; \
         false alarms held to {} for the whole series\n",
        t.machine.label(),
        t.runs.len(),
        t.kind,
        t.runs.first().map_or("?", |r| r.run.started_at.as_str()),
        t.runs.last().map_or("?", |r| r.run.started_at.as_str()),
        t.parameters.len(),
        t.tests,
        t.alpha
    );
    for note in &t.notes {
        out += &format!("  note: {note}\n");
    }
    if t.events.is_empty() {
        out += "\nNo event: no step, drift or value outside its tolerance band.\n";
    } else {
        out += &format!("\nEvents, {}:\n", t.events.len());
        for e in &t.events {
            out += &format!("  {:<17} {}\n", kind_name(e.kind), e.message);
        }
    }
    out
}

fn kind_name(kind: EventKind) -> &'static str {
    match kind {
        EventKind::Step => "step",
        EventKind::Drift => "drift",
        EventKind::OutsideTolerance => "outside tolerance",
    }
}

/// How many parameter panels the report draws: those with events first, then the rest.
const REPORT_PANELS: usize = 24;

/// The HTML/Markdown report: the runs, the events, and each parameter over time with ±2σ and
/// its band.
pub fn document(t: &Trend) -> anyhow::Result<crate::document::Document> {
    use crate::document::plots::{panels_svg, Panel, Series, Style};
    use crate::document::{Document, Section, Table};
    let mut summary = Section::new("trend", "Trend").facts(vec![
        ("machine".into(), t.machine.label()),
        ("kind".into(), t.kind.clone()),
        ("runs".into(), t.runs.len().to_string()),
        ("parameters".into(), t.parameters.len().to_string()),
        (
            "false-alarm level".into(),
            format!("{} ({})", t.alpha, t.correction),
        ),
        ("events".into(), t.events.len().to_string()),
    ]);
    for note in &t.notes {
        summary = summary.paragraph(format!("Note: {note}"));
    }
    let mut runs = Table::new("Runs", &["#", "run", "session", "started", "day"]);
    for (i, r) in t.runs.iter().enumerate() {
        runs.row(vec![
            (i + 1).to_string(),
            r.run.label.clone(),
            r.run.session_id.clone(),
            r.run.started_at.clone(),
            format!("{:.2}", r.t_days),
        ]);
    }
    summary = summary.table(runs);
    let mut events = Section::new("events", "Events");
    if t.events.is_empty() {
        events = events.paragraph("No step, drift or value outside its tolerance band.");
    } else {
        let mut table = Table::new("Events", &["run", "event", "parameter", "what"]);
        for e in &t.events {
            table.row(vec![
                (e.run + 1).to_string(),
                kind_name(e.kind).into(),
                short(&e.parameter),
                e.message.clone(),
            ]);
        }
        events = events.table(table);
    }
    let mut order: Vec<&ParameterTrend> = t.parameters.iter().collect();
    let has_event = |p: &ParameterTrend| t.events.iter().any(|e| e.parameter == p.id);
    order.sort_by_key(|p| !has_event(p));
    let panels: Vec<Panel> = order
        .iter()
        .take(REPORT_PANELS)
        .map(|p| {
            let unit = display(1.0, &p.unit).1;
            let points: Vec<(f64, f64)> = p
                .values
                .iter()
                .zip(&t.runs)
                .map(|(v, r)| (r.t_days, v.map_or(f64::NAN, |v| display(v, &p.unit).0)))
                .collect();
            let band2: Vec<f64> = p
                .sigmas
                .iter()
                .map(|s| s.map_or(f64::NAN, |s| 2.0 * display(s, &p.unit).0))
                .collect();
            let mut series = vec![Series::line("value ± 2σ", points).with_band(band2)];
            if let Some(b) = &p.band {
                let ends = [
                    t.runs.first().map_or(0.0, |r| r.t_days),
                    t.runs.last().map_or(1.0, |r| r.t_days),
                ];
                for (name, sign) in [("band", 1.0), ("band ", -1.0)] {
                    series.push(
                        Series::line(
                            name,
                            ends.iter()
                                .map(|x| (*x, display(b.centre + sign * b.half_width, &p.unit).0))
                                .collect(),
                        )
                        .with_style(Style::Line),
                    );
                }
            }
            Panel {
                title: short(&p.id),
                x_label: "day".into(),
                y_label: unit.to_string(),
                series,
            }
        })
        .collect();
    let mut sections = vec![summary, events];
    if !panels.is_empty() {
        let svg = panels_svg("Parameters over time (±2σ, tolerance band)", &panels, 3)?;
        let shown = panels.len();
        let mut section =
            Section::new("parameters", "Parameters over time").plot(crate::document::Plot {
                id: "trend-parameters".into(),
                caption: format!(
                    "{shown} of {} parameters, those with events first",
                    t.parameters.len()
                ),
                svg,
            });
        if t.parameters.len() > shown {
            section = section.paragraph(format!(
                "{} more parameters in the JSON (geocal trend --json).",
                t.parameters.len() - shown
            ));
        }
        sections.push(section);
    }
    Ok(Document {
        title: format!("geocal trend: {}", t.machine.label()),
        sections,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn series(values: &[f64], sigma: f64) -> Vec<Run> {
        let t0 = chrono::DateTime::parse_from_rfc3339("2026-01-01T00:00:00Z")
            .expect("time")
            .with_timezone(&chrono::Utc);
        values
            .iter()
            .enumerate()
            .map(|(i, v)| {
                Run::from_results(
                    &format!("run{i:02}"),
                    serde_json::json!({
                        "format": "geocal-results/1", "kind": "k", "session_id": format!("s{i}"),
                        "squareness": {"xy": {"value_rad": v, "sigma_rad": sigma}},
                    }),
                    MachineIdentity {
                        name: Some("M".into()),
                        serial: None,
                        id: None,
                    },
                    Some(t0 + chrono::Duration::days(7 * i as i64)),
                )
                .expect("run")
            })
            .collect()
    }

    #[test]
    fn a_clear_step_is_found_where_it_happens() {
        let values = [0.1, -0.2, 0.0, 0.1, -0.1, 0.2, 5.1, 4.9, 5.0, 5.2, 4.8, 5.0];
        let runs = series(&values.map(|v| v * 1e-6), 1e-6);
        let t = trend(&runs, &TrendOptions::default()).expect("trend");
        let steps: Vec<&Event> = t
            .events
            .iter()
            .filter(|e| e.kind == EventKind::Step)
            .collect();
        assert_eq!(steps.len(), 1, "{:#?}", t.events);
        assert_eq!(steps[0].run, 6);
        assert!(text(&t).contains("step"));
        assert_eq!(document(&t).expect("doc").plots().count(), 1);
    }

    #[test]
    fn a_ramp_is_a_drift_with_its_rate() {
        // 0.1 µrad per week, σ 0.05 µrad.
        let values: Vec<f64> = (0..12).map(|i| 0.1e-6 * i as f64).collect();
        let runs = series(&values, 0.05e-6);
        let t = trend(&runs, &TrendOptions::default()).expect("trend");
        let drift = t
            .events
            .iter()
            .find(|e| e.kind == EventKind::Drift)
            .expect("drift");
        let rate = drift.rate_per_day.expect("rate");
        assert!((rate - 0.1e-6 / 7.0).abs() < 1e-12, "{rate}");
    }
}
