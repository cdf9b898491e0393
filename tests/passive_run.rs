//! Passive mode: the simulated machine runs the exported NC program by itself, with
//! unplanned stops and dwell jitter; the sequencer only watches the tracer. The run must
//! recover the truth like the active demo, and report every unplanned stop.

use crate::common;

use common::{assert_recovers_truth, run_with_truth, small_demo};
use geocal::config::Config;
use geocal::plan::nc::{parse_gcode, NcBlock};
use geocal::plan::Plan;
use geocal::session::messages::RunEvent;
use geocal::session::reader::read_session;

/// Moves (0-based program order) that pause part way, where, and how long: a long pause
/// mid-move, a short one, one just before the point (its length matches, its duration does
/// not), and one on the way back to point 0 at a pass start.
const STOPS: [(usize, f64, f64); 4] = [
    (3, 0.5, 5.0),
    (20, 0.3, 1.5),
    (50, 0.98, 2.0),
    (90, 0.6, 30.0),
];

fn passive_config() -> String {
    let stops: Vec<String> = STOPS
        .iter()
        .map(|(m, f, d)| format!("{{ move_index = {m}, fraction = {f}, duration_s = {d} }}"))
        .collect();
    let text = small_demo().replace(
        "driver = \"sim\"\nfeed_m_s",
        "driver = \"passive\"\nfeed_m_s",
    );
    assert!(text.contains("\"passive\""));
    format!(
        "{text}\n[sim.passive]\ndwell_jitter_s = 0.5\nunplanned_stops = [{}]\n",
        stops.join(", ")
    )
}

#[test]
fn a_passive_run_recovers_the_truth_and_reports_every_unplanned_stop() {
    let text = passive_config();
    let dir = tempfile::tempdir().expect("tempdir");
    let (output, truth) = run_with_truth(&text, dir.path());
    let results = output.results.multilateration().expect("tracer results");
    assert_recovers_truth(results, &truth);

    // Every plan point measured once per pass, as in an active run.
    let config = Config::parse(&text, std::path::Path::new("passive.toml")).expect("config");
    let plan = Plan::from_config(&config);
    let windows = plan.stations.len() * plan.passes.len() * plan.points.len();
    assert_eq!(results.extraction.windows_used, windows);

    // The program's moves in order: (station, pass, point) each leads to.
    let mut moves = vec![];
    for station in &plan.stations {
        for (pass, &direction) in plan.passes.iter().enumerate() {
            for point in plan.pass_order(direction) {
                moves.push((station.id.clone(), pass, point));
            }
        }
    }
    let reported: Vec<(String, usize, usize)> = read_session(&output.session_path)
        .expect("session")
        .events
        .into_iter()
        .filter_map(|e| match e.msg {
            RunEvent::UnplannedStop {
                station,
                pass,
                point,
                ..
            } => Some((station.to_string(), pass, point)),
            _ => None,
        })
        .collect();
    let injected: Vec<_> = STOPS.iter().map(|s| moves[s.0].clone()).collect();
    println!("unplanned stops reported: {reported:?}");
    assert_eq!(
        reported, injected,
        "each unplanned stop reported once, at its move"
    );
}

#[test]
fn export_nc_writes_the_program_the_plan_describes() {
    let dir = tempfile::tempdir().expect("tempdir");
    let config_path = dir.path().join("passive.toml");
    std::fs::write(&config_path, passive_config()).expect("config");
    let out = dir.path().join("plan.nc");
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_geocal"))
        .arg("export-nc")
        .arg(&config_path)
        .arg("--out")
        .arg(&out)
        .status()
        .expect("geocal");
    assert!(status.success());
    let text = std::fs::read_to_string(&out).expect("program");
    let blocks = parse_gcode(&text).expect("parse");
    let config = Config::load(&config_path).expect("config");
    let plan = Plan::from_config(&config);
    let moves: Vec<[f64; 3]> = blocks
        .iter()
        .filter_map(|b| match b {
            NcBlock::Move { axes_m, .. } => Some(*axes_m),
            _ => None,
        })
        .collect();
    let mut want = vec![];
    for _ in &plan.stations {
        for &direction in &plan.passes {
            for point in plan.pass_order(direction) {
                want.push(plan.points[point].axes_m);
            }
        }
    }
    assert_eq!(moves.len(), want.len());
    for (m, w) in moves.iter().zip(&want) {
        for k in 0..3 {
            assert!((m[k] - w[k]).abs() < 1e-7, "{m:?} vs {w:?}");
        }
    }
    let stops = blocks
        .iter()
        .filter(|b| matches!(b, NcBlock::Stop { .. }))
        .count();
    assert_eq!(
        stops,
        plan.stations.len() + 1,
        "one per station, one to mount t0"
    );
    let dwells = blocks
        .iter()
        .filter(|b| matches!(b, NcBlock::Dwell { s } if *s > plan.dwell_s))
        .count();
    assert_eq!(
        dwells,
        want.len(),
        "a dwell longer than the plan's after every move"
    );
}
