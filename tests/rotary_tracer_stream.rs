//! `geocal solve` streams a clean rotary_tracer session (the tracer samples go straight to the
//! extraction; the table's events and states are kept) and gives the whole read's results to
//! the bit; a cut copy is not streamed.

use crate::common;

use geocal::kinds::rotary_tracer::solve::{solve, solve_file_streaming};
use geocal::method::SolveSettings;
use geocal::session::reader::read_session;

#[test]
fn streamed_rotary_tracer_solve_equals_the_whole_read() {
    let dir = tempfile::tempdir().expect("tempdir");
    let config = common::reduced_rotary(90f64.to_radians(), 4, "");
    let (output, _truth) = common::run_with_truth(&config, dir.path());
    let path = &output.session_path;
    let settings = SolveSettings::default();

    let streamed = solve_file_streaming(path, &settings)
        .expect("a clean session streams")
        .expect("the streamed session solves");
    let whole = solve(&read_session(path).expect("session"), &settings).expect("solves");
    assert_eq!(
        serde_json::to_string(&streamed).expect("json"),
        serde_json::to_string(&whole).expect("json"),
        "the streamed solve differs from the whole read's"
    );
    // The table's recorded states and rotations reached the streamed solve.
    assert_eq!(streamed.rotary.steps.len(), 4);
    assert!(
        streamed
            .rotary
            .steps
            .iter()
            .all(|s| s.encoder_rad.is_some()),
        "{:?}",
        streamed.rotary.steps
    );

    let bytes = std::fs::read(path).expect("read");
    let cut = dir.path().join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).expect("write");
    assert!(
        solve_file_streaming(&cut, &settings).is_none(),
        "a cut file is read whole"
    );
}
