//! The report of a verification run (a run whose machine applied compensation tables): the
//! tables applied, and per compensated error before vs after with the pass rule's verdict.
//! "Before" is the results file the tables' `geocal-source.json` names, or `--before`.

use std::path::{Path, PathBuf};

use crate::compensate::applied::AppliedFile;
use crate::compensate::source::sha256_hex;
use crate::compensate::verify::{compare, Comparison};
use crate::compensate::{Calibration, AXES};
use crate::document::plots::{panels_svg, Panel, Series, Style};
use crate::document::{um, KindReport, Plot, Section, Table};
use crate::session::messages::DeviceInfo;

use super::Inputs;

const TITLE: &str = "Verification run: before and after compensation";

pub fn sections(inputs: &Inputs, _: &KindReport) -> anyhow::Result<Vec<Section>> {
    let Some(machine) = inputs.session.as_ref().and_then(|s| {
        s.header
            .devices
            .iter()
            .find(|d| d.kind == "machine" && d.extra.contains_key("compensation"))
    }) else {
        return Ok(Vec::new());
    };
    let section = Section::new("verification", TITLE).paragraph(
        "The machine of this run applied compensation tables as its controller would (linear \
         interpolation, end values beyond the table): the same plan measures what is left. \
         Pass rule per compensated error: RMS(after) ≤ 2·RMS(σ) + interpolation error, σ the \
         before calibration's and this run's σ combined at each position, the interpolation \
         error the largest departure of the tables from the before curve \
         (docs/compensation.md).",
    );
    let (applied, unreadable) = applied_files(machine);
    if applied.is_empty() {
        return Ok(vec![section.paragraph(format!(
            "This session lists the tables applied ({}) but not what they held{}: no \
             before/after comparison.",
            machine
                .extra
                .get("compensation")
                .map(|v| v.to_string())
                .unwrap_or_default(),
            unreadable
                .first()
                .map(|e| format!(" ({e})"))
                .unwrap_or_default()
        ))]);
    }
    let mut section = section.table(tables_applied(&applied));
    if let Some(session) = inputs.session.as_ref() {
        section = controller_trims(session, section);
    }
    for e in &unreadable {
        section = section.paragraph(format!("A table could not be recorded: {e}."));
    }
    let before = match before_results(inputs, &applied) {
        Ok((calibration, notes)) => {
            for n in notes {
                section = section.paragraph(n);
            }
            calibration
        }
        Err(message) => return Ok(vec![section.paragraph(message)]),
    };
    let after = match Calibration::load(&inputs.results_path) {
        Ok(c) => c,
        Err(e) => {
            return Ok(vec![section.paragraph(format!(
                "This run's results hold no errors to compare: {e}"
            ))])
        }
    };
    let records: Vec<_> = applied.iter().flat_map(|a| a.tables.clone()).collect();
    let mut comparisons = Vec::new();
    for c in compare(&before, &after, &records) {
        match c {
            Ok(c) => comparisons.push(c),
            Err(message) => section = section.paragraph(format!("Not compared: {message}.")),
        }
    }
    if comparisons.is_empty() {
        return Ok(vec![
            section.paragraph("No compensated error could be compared.")
        ]);
    }
    let passed = comparisons.iter().filter(|c| c.passes()).count();
    section = section
        .facts(vec![
            (
                "before".into(),
                format!(
                    "{} (session {}, SHA-256 {})",
                    before.source.display(),
                    before.session_id,
                    before.source_sha256
                ),
            ),
            (
                "after".into(),
                format!("this run (session {})", after.session_id),
            ),
            (
                "verdict".into(),
                format!(
                    "{passed} of {} compensated errors within 2σ + interpolation error: {}",
                    comparisons.len(),
                    if passed == comparisons.len() {
                        "pass"
                    } else {
                        "FAIL"
                    }
                ),
            ),
        ])
        .table(verdicts(&comparisons))
        .plot(Plot {
            id: "verification-before-after".into(),
            caption: "Each compensated error before (the calibration the tables came from) \
                      and after (this run), ±2σ shaded, and what the tables remove."
                .into(),
            svg: panels_svg(
                "Before and after compensation",
                &comparisons
                    .iter()
                    .map(before_after_panel)
                    .collect::<Vec<_>>(),
                3,
            )?,
        })
        .plot(Plot {
            id: "verification-after".into(),
            caption: "What is left after compensation, on its own scale: ±2σ shaded (before \
                      and after combined) and the pass bound ±(2·RMS σ + interpolation error)."
                .into(),
            svg: panels_svg(
                "After compensation",
                &comparisons.iter().map(after_panel).collect::<Vec<_>>(),
                3,
            )?,
        });
    Ok(vec![section])
}

/// A point where the trim the controller applied differs from its table's value by more than
/// this was not compensated as the table says (LinuxCNC's dead band, docs/linuxcnc.md).
const TRIM_MISMATCH_M: f64 = 1e-9;

/// The trims the controller applied at each point (`controller_trims` events, a real
/// controller in the loop): per joint, how far the applied trim stood from the table's value,
/// and the points where the controller's dead band kept a correction from being applied.
fn controller_trims(session: &crate::session::reader::Session, section: Section) -> Section {
    use crate::session::messages::RunEvent;
    let mut per_joint: Vec<(usize, f64, f64, Vec<String>)> = Vec::new();
    let mut points = 0usize;
    for e in &session.events {
        let RunEvent::ControllerTrims {
            station,
            point,
            pass,
            joints,
        } = &e.msg
        else {
            continue;
        };
        points += 1;
        for j in joints {
            if per_joint.len() <= j.joint {
                per_joint.resize(j.joint + 1, (0, 0.0, 0.0, Vec::new()));
            }
            let entry = &mut per_joint[j.joint];
            let gap = (j.table_m - j.applied_m).abs();
            entry.0 += 1;
            entry.1 = entry.1.max(j.applied_m.abs());
            if gap > entry.2 {
                entry.2 = gap;
            }
            if gap > TRIM_MISMATCH_M {
                entry.3.push(format!(
                    "{station} point {point} pass {pass}: table {:.3} µm, applied {:.3} µm",
                    um(j.table_m),
                    um(j.applied_m)
                ));
            }
        }
    }
    if points == 0 {
        return section;
    }
    let mut t = Table::new(
        "Trims the controller applied at the points (read at the end of each dwell: LinuxCNC's \
         joint.N.backlash-corr, the table's value, and joint.N.backlash-filt, the trim applied)",
        &[
            "joint",
            "points",
            "largest trim applied [µm]",
            "largest |table − applied| [µm]",
            "points not compensated as the table says",
        ],
    );
    let mut missed = Vec::new();
    for (k, (n, largest, gap, list)) in per_joint.iter().enumerate() {
        t.row(vec![
            AXES.get(k).map_or(k.to_string(), |a| format!("{k} ({a})")),
            n.to_string(),
            format!("{:.3}", um(*largest)),
            format!("{:.4}", um(*gap)),
            list.len().to_string(),
        ]);
        missed.extend(list.iter().map(|l| format!("joint {k}: {l}")));
    }
    let section = section.table(t);
    if missed.is_empty() {
        section.paragraph(format!(
            "At all {points} points the controller applied its tables' values (to 1 nm): what is \
             left after compensation is not its dead band's."
        ))
    } else {
        let shown: Vec<String> = missed.iter().take(20).cloned().collect();
        section.paragraph(format!(
            "At {} joint positions the trim the controller applied differs from its table's \
             value by more than 1 nm: LinuxCNC's dead band (its compensation follows the table \
             through a rate limiter and never follows a small jump from rest; docs/linuxcnc.md) \
             kept the correction from being applied there. Those points' residuals are the \
             controller's, not the calibration's: {}{}.",
            missed.len(),
            shown.join("; "),
            if missed.len() > shown.len() {
                "; …"
            } else {
                ""
            }
        ))
    }
}

/// The machine device's record of what it applied, and the entries that could not be read.
fn applied_files(machine: &DeviceInfo) -> (Vec<AppliedFile>, Vec<String>) {
    let mut files = Vec::new();
    let mut unreadable = Vec::new();
    let Some(list) = machine
        .extra
        .get("compensation_applied")
        .and_then(|v| v.as_array())
    else {
        return (
            files,
            vec!["the session header has no `compensation_applied`".into()],
        );
    };
    for v in list {
        match serde_json::from_value::<AppliedFile>(v.clone()) {
            Ok(a) => files.push(a),
            Err(e) => unreadable.push(
                v.get("error")
                    .and_then(|e| e.as_str())
                    .map(String::from)
                    .unwrap_or_else(|| format!("compensation_applied: {e}")),
            ),
        }
    }
    (files, unreadable)
}

fn tables_applied(applied: &[AppliedFile]) -> Table {
    let mut t = Table::new(
        "Tables applied (the deviation each removes, tool to workpiece)",
        &[
            "file",
            "format",
            "table",
            "base → compensated",
            "range [mm]",
            "step [mm]",
            "points",
            "values [µm]",
        ],
    );
    for a in applied {
        let file = a
            .file
            .file_name()
            .map(|f| f.to_string_lossy().into_owned())
            .unwrap_or_else(|| a.file.display().to_string());
        for r in &a.tables {
            let (lo, hi) = (
                r.positions_m.first().copied().unwrap_or(0.0),
                r.positions_m.last().copied().unwrap_or(0.0),
            );
            let (min, max) = r
                .deviation_m
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
                    (a.min(*v), b.max(*v))
                });
            t.row(vec![
                file.clone(),
                a.format.clone(),
                r.name.clone(),
                format!("{} → {}", r.base_axis, r.compensated_axis),
                format!("{:.1} … {:.1}", lo * 1e3, hi * 1e3),
                r.step_m()
                    .map_or("uneven".into(), |s| format!("{:.3}", s * 1e3)),
                r.positions_m.len().to_string(),
                format!("{:.3} … {:.3}", um(min), um(max)),
            ]);
        }
    }
    t
}

/// The before results and any notes about them, or the message that says why there are none.
fn before_results(
    inputs: &Inputs,
    applied: &[AppliedFile],
) -> Result<(Calibration, Vec<String>), String> {
    let mut recorded: Vec<(PathBuf, String, String)> = Vec::new();
    for a in applied {
        if let Some(s) = &a.source {
            let entry = (
                s.results.clone(),
                s.results_sha256.clone(),
                s.session_id.clone(),
            );
            if !recorded.contains(&entry) {
                recorded.push(entry);
            }
        }
    }
    let sidecar_errors: Vec<String> = applied
        .iter()
        .filter_map(|a| a.source_error.clone())
        .collect();
    if let Some(path) = &inputs.before_results {
        let calibration = load(path, "given with --before")?;
        let notes = recorded
            .iter()
            .filter(|(_, sha, _)| *sha != calibration.source_sha256)
            .map(|(p, sha, session)| {
                format!(
                    "Note: the tables were made from {} (session {session}, SHA-256 {sha}); the \
                     before results given with --before are another file (SHA-256 {}): the \
                     comparison is against a calibration the tables did not come from, and the \
                     interpolation error includes their difference.",
                    p.display(),
                    calibration.source_sha256
                )
            })
            .collect();
        return Ok((calibration, notes));
    }
    let no_source = |why: String| {
        format!(
            "{why}, so the results they were made from are not known: give them with `geocal \
             report DIR --before RESULTS`."
        )
    };
    match recorded.as_slice() {
        [] => Err(no_source(match sidecar_errors.first() {
            Some(e) => format!("The tables' geocal-source.json cannot be read ({e})"),
            None => "No geocal-source.json lay beside the tables when they were applied".into(),
        })),
        [(path, sha, session)] => {
            if !path.is_file() {
                return Err(format!(
                    "The before results {} (session {session}, named by the tables' \
                     geocal-source.json) are not there: give them with `geocal report DIR \
                     --before RESULTS`.",
                    path.display()
                ));
            }
            let bytes = std::fs::read(path)
                .map_err(|e| format!("The before results {}: {e}", path.display()))?;
            let now = sha256_hex(&bytes);
            if now != *sha {
                return Err(format!(
                    "The before results {} changed since the tables were made from them \
                     (SHA-256 {now}, recorded {sha}, session {session}): no comparison; give \
                     the original with `geocal report DIR --before RESULTS`.",
                    path.display()
                ));
            }
            Ok((load(path, "named by geocal-source.json")?, Vec::new()))
        }
        several => Err(format!(
            "The tables were made from different results ({}): give the before results with \
             `geocal report DIR --before RESULTS`.",
            several
                .iter()
                .map(|(p, sha, _)| format!("{} SHA-256 {sha}", p.display()))
                .collect::<Vec<_>>()
                .join("; ")
        )),
    }
}

fn load(path: &Path, how: &str) -> Result<Calibration, String> {
    Calibration::load(path).map_err(|e| format!("The before results ({how}) cannot be used: {e}"))
}

fn verdicts(comparisons: &[Comparison]) -> Table {
    let mut t = Table::new(
        "Before and after (RMS and largest |value| over the calibrated positions)",
        &[
            "error",
            "RMS before [µm]",
            "max before [µm]",
            "RMS after [µm]",
            "max after [µm]",
            "RMS σ [µm]",
            "interpolation [µm]",
            "bound [µm]",
            "verdict",
        ],
    );
    for c in comparisons {
        t.row(vec![
            c.name.clone(),
            format!("{:.3}", um(c.rms_before_m())),
            format!("{:.3}", um(c.max_before_m())),
            format!("{:.3}", um(c.rms_after_m())),
            format!("{:.3}", um(c.max_after_m())),
            format!("{:.3}", um(c.sigma_rms_m())),
            format!("{:.4}", um(c.interpolation_error_m)),
            format!("{:.3}", um(c.bound_m())),
            verdict(c).into(),
        ]);
    }
    t
}

fn xy(c: &Comparison, values_m: &[f64]) -> Vec<(f64, f64)> {
    c.positions_m
        .iter()
        .zip(values_m)
        .map(|(q, v)| (*q, um(*v)))
        .collect()
}

fn two_sigma_um(sigma_m: &[f64]) -> Vec<f64> {
    sigma_m.iter().map(|s| 2.0 * um(*s)).collect()
}

fn verdict(c: &Comparison) -> &'static str {
    if c.passes() {
        "pass"
    } else {
        "FAIL"
    }
}

/// The table first, so that the before curve it follows is drawn over it.
fn before_after_panel(c: &Comparison) -> Panel {
    Panel {
        title: format!("{}: {}", c.name, verdict(c)),
        x_label: format!("{} [m]", AXES[c.base]),
        y_label: "µm".into(),
        series: vec![
            Series::line("table", xy(c, &c.tables_m)).with_style(Style::Line),
            Series::line("before", xy(c, &c.before_m)).with_band(two_sigma_um(&c.sigma_before_m)),
            Series::line("after", xy(c, &c.after_m)).with_band(two_sigma_um(&c.sigma_m())),
        ],
    }
}

fn after_panel(c: &Comparison) -> Panel {
    let bound = um(c.bound_m());
    let ends = |v: f64| {
        let first = c.positions_m.first().copied().unwrap_or(0.0);
        let last = c.positions_m.last().copied().unwrap_or(first);
        vec![(first, v), (last, v)]
    };
    Panel {
        title: format!(
            "{} after: RMS {:.3} µm, bound {:.3} µm",
            c.name,
            um(c.rms_after_m()),
            bound
        ),
        x_label: format!("{} [m]", AXES[c.base]),
        y_label: "µm".into(),
        series: vec![
            Series::line("after", xy(c, &c.after_m)).with_band(two_sigma_um(&c.sigma_m())),
            Series::line("bound", ends(bound)).with_style(Style::Line),
            Series::line("", ends(-bound)).with_style(Style::Line),
        ],
    }
}
