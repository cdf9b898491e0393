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

// --- plan kind rotary_tracer ---

const ROTARY: &str = include_str!("../config/rotary-tracer.toml");

/// Replace `from` (which must occur) in the rotary example.
fn rotary_with(from: &str, to: &str) -> String {
    assert!(ROTARY.contains(from), "rotary example lacks {from:?}");
    ROTARY.replace(from, to)
}

#[test]
fn rotary_config_is_valid_and_expands_to_13_stations() {
    let config = parse(ROTARY).expect("rotary config must be valid");
    let plan = geocal::plan::Plan::from_config(&config);
    assert_eq!(plan.stations.len(), 13);
    assert_eq!(plan.points.len(), 72);
    let on_table: Vec<f64> = plan
        .stations
        .iter()
        .filter_map(|s| s.rotation.as_ref().map(|r| r.commanded_rad))
        .collect();
    assert_eq!(on_table.len(), 12);
    assert!((on_table[11] - 330f64.to_radians()).abs() < 1e-12);
    assert_eq!(plan.stations[0].id, "c01");
    assert_eq!(plan.stations[12].id, "s13");
    // Hints turn about the nominal axis with the commanded angle.
    let h = plan.stations[3].hint_m.expect("hint");
    assert!((h[0] - 0.40).abs() < 1e-12 && (h[1] - 0.60).abs() < 1e-12);
}

#[test]
fn rotary_kind_without_table_section() {
    let cut = ROTARY.find("[plan.rotary]").expect("plan.rotary");
    let end = ROTARY
        .find("# The station off the table")
        .expect("station comment");
    let text = format!("{}{}", &ROTARY[..cut], &ROTARY[end..]);
    assert_mentions(&error_of(&text), &[FILE, "plan.rotary", "missing"]);
}

#[test]
fn rotary_kind_without_table_device() {
    let text = rotary_with("[devices.rotary_table]\nid = \"c\"\ndriver = \"sim\"\n", "");
    assert_mentions(&error_of(&text), &[FILE, "devices.rotary_table", "missing"]);
}

#[test]
fn rotary_table_id_must_match_the_device() {
    let text = rotary_with("table = \"c\"", "table = \"b\"");
    assert_mentions(
        &error_of(&text),
        &[FILE, "plan.rotary.table", "`b`", "expected `c`"],
    );
}

#[test]
fn rotary_angles_listed_and_stepped_is_ambiguous() {
    let text = rotary_with("count = 12", "count = 12\nangles_rad = [0.0, 1.0, 2.0]");
    assert_mentions(&error_of(&text), &[FILE, "plan.rotary", "not both"]);
}

#[test]
fn rotary_angles_in_degrees_are_caught() {
    let text = rotary_with(
        "step_rad = 0.5235987755982988           # 30°\ncount = 12",
        "angles_rad = [0.0, 90.0, 180.0, 270.0]",
    );
    assert_mentions(
        &error_of(&text),
        &[FILE, "plan.rotary.angles_rad", "radians", "not degrees"],
    );
}

#[test]
fn rotary_repeated_angle_is_rejected() {
    let text = rotary_with(
        "step_rad = 0.5235987755982988",
        "step_rad = 3.141592653589793",
    );
    assert_mentions(
        &error_of(&text),
        &[FILE, "plan.rotary.count", "same place", "modulo 2π"],
    );
}

#[test]
fn rotary_needs_three_table_stations() {
    let text = rotary_with("count = 12", "count = 2");
    assert_mentions(
        &error_of(&text),
        &[FILE, "plan.rotary.count", "at least 3", "found 2"],
    );
}

#[test]
fn rotary_tracer_on_the_axis_is_rejected() {
    let text = rotary_with(
        "tracer_hint_m = [0.60, 0.40, -0.15]",
        "tracer_hint_m = [0.40, 0.40, -0.15]",
    );
    assert_mentions(
        &error_of(&text),
        &[FILE, "plan.rotary.tracer_hint_m", "off-centre"],
    );
}

#[test]
fn rotary_needs_a_station_off_the_table_plane() {
    let text = rotary_with(
        "hint_m = [-0.25, 0.40, 0.30]",
        "hint_m = [-0.25, 0.40, -0.15]",
    );
    assert_mentions(
        &error_of(&text),
        &[FILE, "plan.stations", "one plane", "off the table"],
    );
}

#[test]
fn rotary_unknown_key_is_named() {
    let text = rotary_with("count = 12", "count = 12\nstep_deg = 30.0");
    assert_mentions(
        &error_of(&text),
        &[FILE, "plan.rotary", "unknown field `step_deg`"],
    );
}

#[test]
fn rotary_section_needs_the_rotary_kind() {
    let text = rotary_with("kind = \"rotary_tracer\"", "kind = \"multilateration\"");
    assert_mentions(
        &error_of(&text),
        &[FILE, "plan.rotary", "kind = \"rotary_tracer\""],
    );
}

#[test]
fn rotary_sim_speed_must_be_positive() {
    let text = rotary_with(
        "axis_tilt_rad = 1e-4 }",
        "axis_tilt_rad = 1e-4, speed_rad_s = 0.0 }",
    );
    assert_mentions(
        &error_of(&text),
        &[FILE, "sim.rotary.speed_rad_s", "positive"],
    );
}

#[test]
fn rotary_iso_cycle_keys_are_checked_by_name() {
    let cases = [
        (
            "count = 12",
            "count = 12\nruns = 0",
            "plan.rotary.runs",
            "at least 1",
        ),
        (
            "count = 12",
            "count = 12\novershoot_rad = 0.05",
            "plan.rotary.overshoot_rad",
            "runs = N",
        ),
        (
            "count = 12",
            "count = 12\nruns = 5\novershoot_rad = -0.1",
            "plan.rotary.overshoot_rad",
            "positive angle",
        ),
        (
            "step_rad = 0.5235987755982988           # 30°\ncount = 12",
            "angles_rad = [0.0, 1.0, 2.0]\nspacing = \"pseudo_random\"",
            "plan.rotary.spacing",
            "stepped form",
        ),
        (
            "axis_tilt_rad = 1e-4 }",
            "axis_tilt_rad = 1e-4, reversal_rad = -1e-5 }",
            "sim.rotary.reversal_rad",
            "",
        ),
        (
            "axis_tilt_rad = 1e-4 }",
            "axis_tilt_rad = 1e-4, repeatability_rad = -1e-5 }",
            "sim.rotary.repeatability_rad",
            "",
        ),
    ];
    for (from, to, key, what) in cases {
        assert_mentions(&error_of(&rotary_with(from, to)), &[FILE, key, what]);
    }
    // The cycle itself: 5 runs over 12 angles are 120 table stations and the one off it.
    let config = parse(&rotary_with("count = 12", "count = 12\nruns = 5")).expect("valid");
    let plan = geocal::plan::Plan::from_config(&config);
    assert_eq!(plan.stations.len(), 121);
    assert_eq!(plan.stations[119].id, "c120");
}

#[test]
fn protocol_driver_errors_name_the_key() {
    // A GRBL tracer does not exist.
    let text = DEMO.replace(
        "id = \"tracer0\"\ndriver = \"sim\"",
        "id = \"tracer0\"\ndriver = \"grbl\"",
    );
    assert_mentions(
        &error_of(&text),
        &["devices.tracer.driver", "\"sim\" or \"hpi3d\""],
    );
    // A real GRBL controller needs its port.
    let text = DEMO.replace(
        "driver = \"sim\"\nfeed_m_s = 0.3",
        "driver = \"grbl\"\nfeed_m_s = 0.3",
    );
    assert_mentions(&error_of(&text), &["devices.machine.grbl.port", "missing"]);
    // Emulated runs need the HPI-3D tracer (its stream runs the world's clock).
    let text = format!("{DEMO}\n[hil]\nemulate = true\n");
    assert_mentions(&error_of(&text), &["devices.tracer.driver", "hpi3d"]);
    // Unknown keys in the driver's and the emulator's settings are named.
    let text = format!(
        "{}\n[devices.tracer.hpi3d]\nbaudrate = 9600\n",
        DEMO.replace(
            "id = \"tracer0\"\ndriver = \"sim\"",
            "id = \"tracer0\"\ndriver = \"hpi3d\""
        )
    );
    assert_mentions(&error_of(&text), &["devices.tracer.hpi3d", "baudrate"]);
    let text = format!(
        "{}\n[hil]\ntracer_faults = {{ drop = 0.1 }}\n",
        DEMO.replace(
            "id = \"tracer0\"\ndriver = \"sim\"",
            "id = \"tracer0\"\ndriver = \"hpi3d\""
        )
    );
    assert_mentions(&error_of(&text), &["hil.tracer_faults", "drop"]);
    let text = format!(
        "{}\n[hil]\ntracer_faults = {{ drop_fraction = 1.5 }}\n",
        DEMO.replace(
            "id = \"tracer0\"\ndriver = \"sim\"",
            "id = \"tracer0\"\ndriver = \"hpi3d\""
        )
    );
    assert_mentions(
        &error_of(&text),
        &["hil.tracer_faults.drop_fraction", "[0, 1]"],
    );
}

#[test]
fn uncertainty_section_is_optional_and_strict() {
    let config = parse(DEMO).expect("demo config without [uncertainty]");
    assert!(config.uncertainty.is_none() && config.normalisation.is_none());
    let declared = format!(
        "{DEMO}\n[uncertainty]\nair_temp_k = 0.05\ncte_per_k = 5e-7\n\n[normalisation]\nscale_cte_per_k = 8.5e-6\n"
    );
    let config = parse(&declared).expect("declared uncertainties");
    let u = config.uncertainty.expect("section");
    assert_eq!((u.air_temp_k, u.cte_per_k), (0.05, 5e-7));
    assert_eq!(
        u.pressure_pa, 20.0,
        "a missing key takes its documented default"
    );
    let n = config.normalisation.expect("section");
    assert_eq!(n.scale_cte_per_k, 8.5e-6);

    let message = error_of(&format!("{DEMO}\n[uncertainty]\nair_temp = 0.05\n"));
    assert_mentions(&message, &[FILE, "unknown field `air_temp`", "uncertainty"]);
    let message = error_of(&format!("{DEMO}\n[uncertainty]\nhumidity_pct = -2.0\n"));
    assert_mentions(&message, &[FILE, "uncertainty.humidity_pct", ">= 0"]);
    let message = error_of(&format!(
        "{DEMO}\n[normalisation]\nscale_cte_per_k = 11.5\n"
    ));
    assert_mentions(&message, &[FILE, "normalisation.scale_cte_per_k", "1/K"]);
}
