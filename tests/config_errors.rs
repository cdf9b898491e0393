//! Malformed configurations fail with the file, the key and what was expected.

use std::path::Path;

use geocal::config::{Config, ConfigError};

const DEMO: &str = include_str!("../config/demo-multilateration.toml");
const FILE: &str = "config/test.toml";

fn parse(text: &str) -> Result<Config, ConfigError> {
    Config::parse(text, Path::new(FILE))
}

fn error_of(text: &str) -> String {
    match parse(text) {
        Ok(_) => panic!("config unexpectedly valid"),
        Err(e) => e.to_string(),
    }
}

fn assert_mentions(message: &str, parts: &[&str]) {
    for part in parts {
        assert!(
            message.contains(part),
            "error {message:?} does not mention {part:?}"
        );
    }
}

#[test]
fn demo_config_is_valid() {
    let config = parse(DEMO).expect("demo config must be valid");
    assert_eq!(config.plan.stations.len(), 5);
}

#[test]
fn missing_key_names_it() {
    let text = DEMO.replace("structure = \"FYXZ\"", "");
    let message = error_of(&text);
    assert_mentions(&message, &[FILE, "machine", "missing field `structure`"]);
}

#[test]
fn wrong_type_names_key_and_expected_type() {
    let text = DEMO.replace("sample_rate_hz = 25.0", "sample_rate_hz = \"fast\"");
    let message = error_of(&text);
    assert_mentions(
        &message,
        &[FILE, "devices.tracer.sample_rate_hz", "expected"],
    );
}

#[test]
fn unknown_key_is_rejected_with_its_name() {
    let text = DEMO.replace("dwell_s = 2.0", "dwell_s = 2.0\ndwel_time = 3.0");
    let message = error_of(&text);
    assert_mentions(&message, &[FILE, "unknown field `dwel_time`", "plan"]);
}

#[test]
fn fewer_than_four_stations_is_impossible() {
    let cut = DEMO
        .find("[[plan.stations]]\nid = \"s4\"")
        .expect("demo has station s4");
    let sim = DEMO.find("\n[sim]").expect("demo has [sim]");
    let text = format!("{}{}", &DEMO[..cut], &DEMO[sim..]);
    let message = error_of(&text);
    assert_mentions(
        &message,
        &[FILE, "plan.stations", "at least 4 stations", "found 3"],
    );
}

#[test]
fn grid_outside_travel_is_rejected() {
    let text = DEMO.replace("x = { from = 0.1, to = 1.3", "x = { from = 0.1, to = 1.6");
    let message = error_of(&text);
    assert_mentions(&message, &[FILE, "plan.grid.x.to", "outside the travel"]);
}

#[test]
fn unknown_target_lists_the_known_ones() {
    let text = DEMO.replace("targets = [\"t0\"]", "targets = [\"t9\"]");
    let message = error_of(&text);
    assert_mentions(&message, &[FILE, "plan.targets[0]", "t9", "t0"]);
}

#[test]
fn bad_structure_string_is_explained() {
    let text = DEMO.replace("structure = \"FYXZ\"", "structure = \"FYXX\"");
    let message = error_of(&text);
    assert_mentions(&message, &[FILE, "machine.structure"]);
}

#[test]
fn too_few_points_for_the_unknowns() {
    let text = DEMO
        .replace(
            "x = { from = 0.1, to = 1.3, count = 5 }",
            "x = { from = 0.1, to = 1.3, count = 2 }",
        )
        .replace(
            "y = { from = 0.2, to = 2.2, count = 5 }",
            "y = { from = 0.2, to = 2.2, count = 2 }",
        )
        .replace(
            "z = { from = 0.15, to = 0.95, count = 4 }",
            "z = { from = 0.15, to = 0.95, count = 2 }",
        );
    let message = error_of(&text);
    assert_mentions(
        &message,
        &[FILE, "plan.grid", "at least 16 points", "found 8"],
    );
}

#[test]
fn stillstand_window_longer_than_dwell() {
    let text = DEMO.replace("window_s = 0.6", "window_s = 3.0");
    let message = error_of(&text);
    assert_mentions(&message, &[FILE, "plan.stillstand.window_s", "dwell_s"]);
}

#[test]
fn toml_syntax_error_gives_a_line() {
    let message = error_of("kind = \"multilateration\"\n[machine\n");
    assert_mentions(&message, &[FILE, "line 2"]);
}

#[test]
fn unreadable_file_names_it() {
    let err = Config::load(Path::new("no/such/config.toml")).expect_err("must fail");
    assert_mentions(&err.to_string(), &["no/such/config.toml", "cannot read"]);
}
