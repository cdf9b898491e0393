//! A real LinuxCNC (Debian's linuxcnc-uspace) as the machine. One LinuxCNC may run on a
//! machine at a time (docs/linuxcnc.md), so every scenario that starts one runs in
//! [`linuxcnc_scenarios_one_at_a_time`], in turn: as separate tests they would hold test
//! threads while waiting for LinuxCNC's lock, and the rest of the binary would wait with
//! them. `GEOCAL_LINUXCNC_SCENARIO=part` runs the scenarios whose name contains `part`.

mod driver;
mod faults;
mod hil;
mod launch;
mod sample_configs;

use std::time::Instant;

use crate::common;

/// Every scenario that starts LinuxCNC, by name.
const SCENARIOS: &[(&str, fn())] = &[
    (
        "launch::linuxcnc_starts_moves_reports_trim_pins_and_shuts_down_clean",
        launch::linuxcnc_starts_moves_reports_trim_pins_and_shuts_down_clean,
    ),
    (
        "launch::a_missing_comp_file_fails_fast_and_a_dropped_instance_leaves_nothing",
        launch::a_missing_comp_file_fails_fast_and_a_dropped_instance_leaves_nothing,
    ),
    (
        "driver::drives_the_real_linuxcnc_through_faults",
        driver::drives_the_real_linuxcnc_through_faults,
    ),
    (
        "hil::linuxcnc_hil_run_recovers_truth",
        hil::linuxcnc_hil_run_recovers_truth,
    ),
    (
        "hil::linuxcnc_applies_geocal_tables_and_bad_tables_fail_verification",
        hil::linuxcnc_applies_geocal_tables_and_bad_tables_fail_verification,
    ),
    (
        "faults::linuxcnc_run_reconnects_after_a_cut_connection",
        faults::linuxcnc_run_reconnects_after_a_cut_connection,
    ),
    (
        "faults::linuxcnc_run_stopped_by_an_estop_resumes",
        faults::linuxcnc_run_stopped_by_an_estop_resumes,
    ),
    (
        "faults::linuxcnc_run_stopped_by_a_killed_linuxcncrsh_resumes",
        faults::linuxcnc_run_stopped_by_a_killed_linuxcncrsh_resumes,
    ),
    (
        "sample_configs::axis_mm_estop_stops_the_run_and_refusals_change_nothing",
        sample_configs::axis_mm_estop_stops_the_run_and_refusals_change_nothing,
    ),
    (
        "sample_configs::axis_inch_machine_ends_in_g20_with_its_modes",
        sample_configs::axis_inch_machine_ends_in_g20_with_its_modes,
    ),
    (
        "sample_configs::gantry_runs_with_its_four_joints",
        sample_configs::gantry_runs_with_its_four_joints,
    ),
    (
        "sample_configs::axis_mm_whole_run_stopped_by_an_estop_resumes_with_nothing_lost",
        sample_configs::axis_mm_whole_run_stopped_by_an_estop_resumes_with_nothing_lost,
    ),
];

/// Runs every scenario, each to its end whatever the others did, and fails naming those
/// that failed (their panic messages are printed where they happen).
#[test]
fn linuxcnc_scenarios_one_at_a_time() {
    if !common::linuxcnc_available() {
        return;
    }
    let only = std::env::var("GEOCAL_LINUXCNC_SCENARIO").ok();
    let mut failed = Vec::new();
    let mut ran = 0;
    for &(name, scenario) in SCENARIOS {
        if only.as_deref().is_some_and(|part| !name.contains(part)) {
            continue;
        }
        ran += 1;
        let started = Instant::now();
        let outcome = std::panic::catch_unwind(scenario);
        println!(
            "LinuxCNC scenario {name}: {} in {:.1} s",
            if outcome.is_ok() { "ok" } else { "FAILED" },
            started.elapsed().as_secs_f64()
        );
        if outcome.is_err() {
            failed.push(name);
        }
    }
    assert!(ran > 0, "no LinuxCNC scenario matches {only:?}");
    assert!(failed.is_empty(), "LinuxCNC scenarios failed: {failed:#?}");
}
