//! `geocal report` streams a clean multilateration session (the tracer samples never held):
//! the same document as from the session read whole.

use crate::common;

use geocal::kinds::registry::Registry;
use geocal::report::Inputs;
use geocal::session::reader::read_session;

#[test]
fn streamed_report_equals_the_whole_read() {
    let dir = tempfile::tempdir().expect("tempdir");
    let text = common::with_effects(
        &common::small_demo(),
        5,
        "reversal = { enabled = true, size = 1e-6 }",
    );
    let (output, _) = common::run_with_truth(&text, dir.path());
    let streamed = Inputs::read(dir.path()).expect("inputs");
    let settled = streamed.settled.as_ref().expect("a clean session streams");
    assert!(!settled.extraction.measurements.is_empty());
    let light = streamed.session.as_ref().expect("session");
    assert!(light.tracers.is_empty());
    assert!(!light.events.is_empty());
    let mut whole = Inputs::read(dir.path()).expect("inputs");
    whole.session = Some(read_session(&output.session_path).expect("session"));
    whole.settled = None;
    let registry = Registry::standard();
    let a = geocal::report::build(&streamed, &registry).expect("report");
    let b = geocal::report::build(&whole, &registry).expect("report");
    let (a, _) = geocal::document::markdown::render(&a, "r-");
    let (b, _) = geocal::document::markdown::render(&b, "r-");
    assert!(a.contains("ISO 230-2"), "{a}");
    assert_eq!(a, b);
}
