//! The tests that do not wait on real time, as modules of one binary:
//! one link instead of one per file, and their longest tests (the Python package's suite, the
//! reports in a browser, the fleet export in Spark, the budgets' Monte Carlo runs) run beside
//! the others instead of each leaving a core idle. Each file in `tests/` named below is one
//! module: `cargo test --test integration compensate::` runs `tests/compensate.rs`.

#[path = "../ball_bar/mod.rs"]
mod ball_bar;
#[path = "../budget_mc/mod.rs"]
mod budget_mc;
#[path = "../common/mod.rs"]
mod common;
#[path = "../iso230_2_common/mod.rs"]
mod iso230_2_common;

#[path = "../cli.rs"]
mod cli;
#[path = "../compensate.rs"]
mod compensate;
#[path = "../config_errors.rs"]
mod config_errors;
#[path = "../config_rotary_table.rs"]
mod config_rotary_table;
#[path = "../damaged_session.rs"]
mod damaged_session;
#[path = "../demo_run.rs"]
mod demo_run;
#[path = "../diagnose.rs"]
mod diagnose;
#[path = "../diagnose_kinds.rs"]
mod diagnose_kinds;
#[path = "../diagnose_levels.rs"]
mod diagnose_levels;
#[path = "../diagnose_oracle.rs"]
mod diagnose_oracle;
#[path = "../diagnose_rotary.rs"]
mod diagnose_rotary;
#[path = "../diagnose_scale.rs"]
mod diagnose_scale;
#[path = "../diagnose_stream.rs"]
mod diagnose_stream;
#[path = "../diagnose_text.rs"]
mod diagnose_text;
#[path = "../export_parquet.rs"]
mod export_parquet;
#[path = "../fuzz.rs"]
mod fuzz;
#[path = "../hexapod_budget.rs"]
mod hexapod_budget;
#[path = "../hexapod_run.rs"]
mod hexapod_run;
#[path = "../history.rs"]
mod history;
#[path = "../iso230_2_plan.rs"]
mod iso230_2_plan;
#[path = "../iso230_2_python.rs"]
mod iso230_2_python;
#[path = "../iso230_2_rotary.rs"]
mod iso230_2_rotary;
#[path = "../iso230_2_run.rs"]
mod iso230_2_run;
#[path = "../layering.rs"]
mod layering;
#[path = "../misfit.rs"]
mod misfit;
#[path = "../monitor.rs"]
mod monitor;
#[path = "../other_recorder.rs"]
mod other_recorder;
#[path = "../outside_kinds.rs"]
mod outside_kinds;
#[path = "../outside_sessions.rs"]
mod outside_sessions;
#[path = "../passive_run.rs"]
mod passive_run;
#[path = "../pipeline_monte_carlo.rs"]
mod pipeline_monte_carlo;
#[path = "../plan_check_kinds.rs"]
mod plan_check_kinds;
#[path = "../probe_install_budget.rs"]
mod probe_install_budget;
#[path = "../probe_install_run.rs"]
mod probe_install_run;
#[path = "../progress.rs"]
mod progress;
#[path = "../python_package.rs"]
mod python_package;
#[path = "../report.rs"]
mod report;
#[path = "../report_stream.rs"]
mod report_stream;
#[path = "../results_digests.rs"]
mod results_digests;
#[path = "../rotary_run.rs"]
mod rotary_run;
#[path = "../rotary_sphere_budget.rs"]
mod rotary_sphere_budget;
#[path = "../rotary_sphere_run.rs"]
mod rotary_sphere_run;
#[path = "../rotary_tilt.rs"]
mod rotary_tilt;
#[path = "../rotary_tracer_stream.rs"]
mod rotary_tracer_stream;
#[path = "../session_python.rs"]
mod session_python;
#[path = "../sixth_kind.rs"]
mod sixth_kind;
#[path = "../solve_effects.rs"]
mod solve_effects;
#[path = "../unc.rs"]
mod unc;
