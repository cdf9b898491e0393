//! The diagnosis as a person reads it: the summary (at most ten lines: verdict, where, which,
//! how far) on effect-free and effect data, and `geocal diagnose --plot` writing the
//! standardised residuals as SVG, one row per station, before and after the selected effects.

use crate::common;

use std::path::Path;
use std::process::{Command, Output};

use common::{diagnose_demo, record_session, with_effects};
use geocal::diagnose::{plot, summary, SUMMARY_MAX_LINES};

const STATIONS: [&str; 5] = ["s1", "s2", "s3", "s4", "s5"];

fn geocal(args: &[&std::ffi::OsStr]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_geocal"))
        .args(args)
        .output()
        .expect("run geocal")
}

/// The summary block of a printed report: the lines before the first blank one.
fn summary_block(report: &str) -> Vec<&str> {
    report.lines().take_while(|l| !l.is_empty()).collect()
}

/// Well-formed enough for a viewer: one <svg> root, every <text> closed, and the labels.
fn assert_svg(document: &str, labels: &[&str]) {
    assert!(document.starts_with("<svg"), "{}", &document[..80]);
    assert!(document.trim_end().ends_with("</svg>"));
    assert_eq!(document.matches("<svg").count(), 1);
    assert_eq!(
        document.matches("<text").count(),
        document.matches("</text>").count()
    );
    for label in labels {
        assert!(document.contains(label), "no `{label}` in the plot");
    }
}

/// Effect-free simulated data: the summary says nothing is needed, within ten lines; the
/// plot has one row per station and only the nominal model's series.
#[test]
fn effect_free_session_summary_and_plot() {
    let dir = tempfile::tempdir().expect("tempdir");
    let session = record_session(&with_effects(&diagnose_demo(), 102, ""), dir.path());
    let (d, residuals) =
        geocal::kinds::diagnosis::diagnose_file_detailed(&session, &Default::default())
            .expect("diagnose");
    let report = geocal::diagnose::text(&d);
    let lines = summary(&d);
    assert!(lines.len() <= SUMMARY_MAX_LINES, "{report}");
    assert_eq!(summary_block(&report), lines, "{report}");
    assert!(d.selected.is_empty(), "{report}");
    assert_eq!(
        lines[1], "verdict: consistent with the noise model (no effect needed)",
        "{report}"
    );
    assert!(
        lines.contains(&"which: none (no effect needed)".to_string()),
        "{report}"
    );
    assert!(
        lines.iter().any(|l| l.starts_with("how far: gap ")),
        "{report}"
    );

    assert_eq!(residuals.lengths.len(), d.observations);
    assert!(residuals.final_effects.is_empty());
    let document = plot::svg(&d.session_id, &residuals).expect("plot");
    let rows: Vec<String> = STATIONS.iter().map(|s| format!("station {s}")).collect();
    let mut labels: Vec<&str> = rows.iter().map(String::as_str).collect();
    labels.extend(["no effect selected", "before: nominal model"]);
    assert_svg(&document, &labels);
    assert!(!document.contains("after:"));
    // One point per length, and the legend's.
    assert_eq!(document.matches("<circle").count(), d.observations + 1);
}

/// A 1 µm reversal, through the command line: the summary names it with its parameters in
/// µm, the gap closes; `--plot` draws both series for every station; an unwritable plot is
/// a clear error.
#[test]
fn reversal_session_summary_and_plot_from_the_command_line() {
    let dir = tempfile::tempdir().expect("tempdir");
    let session = record_session(
        &with_effects(
            &diagnose_demo(),
            12,
            "reversal = { enabled = true, size = 1e-6 }",
        ),
        dir.path(),
    );
    let svg_path = dir.path().join("residuals.svg");
    let out = geocal(&[
        "diagnose".as_ref(),
        session.as_os_str(),
        "--plot".as_ref(),
        svg_path.as_os_str(),
    ]);
    let report = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{report}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lines = summary_block(&report);
    assert!(lines.len() <= SUMMARY_MAX_LINES, "{report}");
    assert_eq!(lines[1], "verdict: explained by reversal", "{report}");
    let which = lines
        .iter()
        .find(|l| l.starts_with("which: reversal: bx "))
        .unwrap_or_else(|| panic!("no which line\n{report}"));
    assert!(
        which.contains(" ± ") && (which.ends_with(" nm") || which.ends_with(" µm")),
        "{report}"
    );
    let how_far = lines
        .iter()
        .find(|l| l.starts_with("how far: gap "))
        .unwrap_or_else(|| panic!("no how-far line\n{report}"));
    // "how far: gap B → A × noise": before several noise floors, after about one.
    let figures: Vec<f64> = how_far["how far: gap ".len()..]
        .split(" × ")
        .next()
        .expect("gap figures")
        .split(" → ")
        .map(|v| v.parse().expect("a number"))
        .collect();
    assert!(figures[0] > 2.0 && figures[1] < 1.3, "{how_far}");
    assert!(lines.iter().any(|l| l.starts_with("where: ")), "{report}");
    assert!(
        lines
            .iter()
            .any(|l| l.contains("--effects reversal") && l.starts_with("corrected calibration")),
        "{report}"
    );

    let document = std::fs::read_to_string(&svg_path).expect("the plot was written");
    let rows: Vec<String> = STATIONS.iter().map(|s| format!("station {s}")).collect();
    let mut labels: Vec<&str> = rows.iter().map(String::as_str).collect();
    labels.extend(["after reversal", "before: nominal model", "after: reversal"]);
    assert_svg(&document, &labels);
    let lengths: usize = report
        .lines()
        .next()
        .and_then(|l| l.split('(').nth(1))
        .and_then(|l| l.split(' ').next())
        .and_then(|n| n.parse().ok())
        .expect("the number of lengths in the first line");
    assert_eq!(document.matches("<circle").count(), 2 * lengths + 2);

    let unwritable = dir.path().join("no-such-dir").join("plot.svg");
    let out = geocal(&[
        "diagnose".as_ref(),
        session.as_os_str(),
        "--plot".as_ref(),
        unwritable.as_os_str(),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    assert!(
        err.contains("writing the residual plot to") && err.contains("no-such-dir"),
        "{err}"
    );
    assert!(!Path::new(&unwritable).exists());
}
