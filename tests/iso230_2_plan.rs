//! The plan keys for ISO 230-2's cycle: `passes = N` (N bidirectional runs) and
//! `spacing = "pseudo_random"` on a grid axis; `geocal check` accepts them, existing
//! configurations keep their plan.

use std::path::Path;

use geocal::config::{Config, PassDirection};
use geocal::kinds::kind_of_config;
use geocal::plan::Plan;

const DEMO: &str = include_str!("../config/demo-multilateration.toml");
const FILE: &str = "config/test.toml";

fn iso_demo() -> String {
    DEMO.replace("passes = [\"forward\", \"backward\"]", "passes = 5")
        .replace(
            "x = { from = 0.1, to = 1.3, count = 5 }",
            "x = { from = 0.1, to = 1.3, count = 7, spacing = \"pseudo_random\" }",
        )
}

#[test]
fn passes_as_a_number_are_bidirectional_runs() {
    let config = Config::parse(&iso_demo(), Path::new(FILE)).expect("valid");
    assert_eq!(config.plan.passes.len(), 10);
    for (i, d) in config.plan.passes.iter().enumerate() {
        let want = if i % 2 == 0 {
            PassDirection::Forward
        } else {
            PassDirection::Backward
        };
        assert_eq!(*d, want, "pass {i}");
    }
    let plan = Plan::from_config(&config);
    let mut xs: Vec<f64> = plan.points.iter().map(|p| p.axes_m[0]).collect();
    xs.sort_by(f64::total_cmp);
    xs.dedup();
    assert_eq!(xs.len(), 7);
    assert_eq!((xs[0], xs[6]), (0.1, 1.3));
    let intervals: Vec<f64> = xs.windows(2).map(|p| p[1] - p[0]).collect();
    assert!(
        intervals.windows(2).any(|p| (p[0] - p[1]).abs() > 1e-3),
        "{intervals:?}"
    );
}

#[test]
fn existing_configs_keep_their_plan() {
    let config = Config::parse(DEMO, Path::new(FILE)).expect("valid");
    assert_eq!(
        config.plan.passes,
        vec![PassDirection::Forward, PassDirection::Backward]
    );
    let plan = Plan::from_config(&config);
    let xs: Vec<f64> = plan.points.iter().take(5).map(|p| p.axes_m[0]).collect();
    let step = (1.3 - 0.1) / 4.0;
    let equal: Vec<f64> = (0..5).map(|i| 0.1 + step * i as f64).collect();
    assert_eq!(xs, equal);
    // An equally spaced axis serialises as before (no `spacing` key).
    let text = toml::to_string(&config.plan.grid).expect("toml");
    assert!(!text.contains("spacing"), "{text}");
}

#[test]
fn bad_values_name_the_key() {
    let text = DEMO.replace("passes = [\"forward\", \"backward\"]", "passes = \"five\"");
    let message = Config::parse(&text, Path::new(FILE))
        .unwrap_err()
        .to_string();
    for part in [FILE, "passes", "number of bidirectional runs"] {
        assert!(message.contains(part), "{message:?} lacks {part:?}");
    }
    let text = iso_demo().replace("pseudo_random", "random");
    let message = Config::parse(&text, Path::new(FILE))
        .unwrap_err()
        .to_string();
    for part in [FILE, "spacing", "pseudo_random"] {
        assert!(message.contains(part), "{message:?} lacks {part:?}");
    }
}

#[test]
fn geocal_check_accepts_the_standard_cycle() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("iso.toml");
    std::fs::write(&path, iso_demo()).expect("write");
    let kind = kind_of_config(&path).expect("kind");
    let check = kind.check(&path).expect("check");
    println!("{}", check.text);
    assert!(!check.text.is_empty());
}
