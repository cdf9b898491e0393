//! `geocal diagnose` and `geocal solve --effects` stream a clean session: the observations the
//! diagnosis builds from the streamed settled windows are exactly those of the whole read, on
//! simulated sessions of the demo and on another recorder's sessions (tests/data/outside,
//! copies of ../shared/sessions); the effects' fit gives the same calibration.

use crate::common;

use std::path::{Path, PathBuf};

use common::{diagnose_demo, record_session, two_target_diagnose_demo, with_effects};
use geocal::extract::{
    stream_dwells, stream_settled, SettledDwells, SettledSession, WindowSamples,
};
use geocal::kinds::tracer_plan::diagnosis::data::Data;
use geocal::session::reader::read_session;

/// Every field of `streamed` equals the whole read's (compared by their exact `{:?}`: every
/// f64 printed to the bit); a field added to `Data` must be added here.
fn assert_same_data(streamed: &Data, whole: &Data, name: &str) {
    let Data {
        session_id,
        obs,
        station_ids,
        passes,
        pass_names,
        pass_zeroings,
        problem,
        nominal,
        station_start_s,
        has_env,
        has_material,
        windows,
        dropped_windows,
        points,
        point_axes_m,
        machine,
        declared_dead_path_m,
        header,
        rotations,
    } = whole;
    let same = |field: &str, a: String, b: String| {
        assert!(
            a == b,
            "{name}: `{field}` differs\nstreamed {a}\nwhole    {b}"
        );
    };
    macro_rules! check {
        ($($field:ident),*) => {
            $(same(stringify!($field), format!("{:?}", streamed.$field), format!("{:?}", $field));)*
        };
    }
    check!(
        session_id,
        obs,
        station_ids,
        passes,
        pass_names,
        pass_zeroings,
        problem,
        nominal,
        station_start_s,
        has_env,
        has_material,
        windows,
        dropped_windows,
        points,
        point_axes_m,
        machine,
        declared_dead_path_m,
        header,
        rotations
    );
}

fn is_multilateration(kind: &str) -> bool {
    kind == "multilateration"
}

/// The streamed settled session of `path` (it must stream) and the whole read's.
fn both(path: &Path) -> (SettledSession, SettledSession) {
    let streamed = stream_settled(path, is_multilateration)
        .unwrap_or_else(|| panic!("{} does not stream", path.display()));
    let session = read_session(path).expect("session");
    let whole = SettledSession::of_session(&session).expect("settled");
    (streamed, whole)
}

fn check_session(path: &Path, name: &str) -> SettledSession {
    let (streamed, whole) = both(path);
    assert_eq!(streamed, whole, "{name}");
    let session = read_session(path).expect("session");
    let from_whole = Data::from_session(&session).expect("data");
    let from_stream = Data::from_settled(streamed.clone()).expect("data");
    assert_same_data(&from_stream, &from_whole, name);
    // The compact form the diagnosis reads: streamed as the whole read's, the same data.
    let compact = stream_dwells(path, is_multilateration, WindowSamples::Kept)
        .unwrap_or_else(|| panic!("{} does not stream compact", path.display()));
    assert_eq!(compact, SettledDwells::of_settled(whole.clone()), "{name}");
    // Without the windows' samples (what the calibration's effects fit reads): the same
    // windows, arrivals and data but for the samples, borrowed or not.
    let arrivals = stream_dwells(path, is_multilateration, WindowSamples::ArrivalOnly)
        .unwrap_or_else(|| panic!("{} does not stream arrivals", path.display()));
    assert_eq!(arrivals, compact.clone().without_window_samples(), "{name}");
    assert!(arrivals
        .windows
        .iter()
        .flatten()
        .all(|w| w.samples.is_empty()));
    let mut from_arrivals = Data::of_dwells(&arrivals).expect("data");
    assert!(from_arrivals.windows.is_empty());
    from_arrivals.windows = from_whole.windows.clone();
    assert_same_data(&from_arrivals, &from_whole, name);
    let from_compact = Data::from_dwells(compact).expect("data");
    assert_same_data(&from_compact, &from_whole, name);
    assert!(
        from_whole.obs.len() > 100,
        "{name}: {}",
        from_whole.obs.len()
    );
    assert!(from_whole.windows.iter().filter(|w| w.is_some()).count() > 100);
    streamed
}

fn outside(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/outside")
        .join(name)
        .join("session.mcap")
}

#[test]
fn streamed_observations_equal_the_whole_read() {
    let dir = tempfile::tempdir().expect("tempdir");
    // The demo with an environment log, warming air and a reversal; and with two targets.
    let reversal = with_effects(
        &diagnose_demo(),
        41,
        "reversal = { enabled = true, size = 1e-6 }",
    );
    let one = dir.path().join("one");
    let two = dir.path().join("two");
    std::fs::create_dir_all(&one).expect("dir");
    std::fs::create_dir_all(&two).expect("dir");
    let one = record_session(&reversal, &one);
    let two = record_session(&with_effects(&two_target_diagnose_demo(), 7, ""), &two);
    let settled = check_session(&one, "demo with reversal");
    assert!(settled.env.values().any(|v| !v.is_empty()));
    check_session(&two, "two targets");
    for name in ["outside-clean-7", "outside-reversal-8"] {
        check_session(&outside(name), name);
    }
}

/// `geocal solve --effects` streams the settled windows: the same results as the whole read.
#[test]
fn effects_fit_of_the_stream_equals_the_whole_read() {
    let path = outside("outside-reversal-8");
    let settings = geocal::method::SolveSettings {
        effects: geocal::kinds::tracer_plan::diagnosis::correct::parse_effects(&[
            "reversal".to_string()
        ])
        .expect("effects"),
        ..Default::default()
    };
    let streamed = geocal::method::multilateration::solve_file_streaming(&path, &settings)
        .expect("streams")
        .expect("solve");
    let session = read_session(&path).expect("session");
    let whole = geocal::method::multilateration::solve(&session, &settings).expect("solve");
    assert_eq!(streamed, whole);
    assert!(
        whole.effects.contains_key("reversal"),
        "{:?}",
        whole.effects
    );
}

/// A file the stream cannot reproduce (cut short) is read whole, as before.
#[test]
fn a_cut_file_is_read_whole() {
    let path = outside("outside-clean-7");
    let bytes = std::fs::read(&path).expect("read");
    let dir = tempfile::tempdir().expect("tempdir");
    let cut = dir.path().join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 3 / 4]).expect("write");
    assert!(stream_settled(&cut, is_multilateration).is_none());
    assert!(stream_dwells(&cut, is_multilateration, WindowSamples::ArrivalOnly).is_none());
    for keep in [WindowSamples::Kept, WindowSamples::ArrivalOnly] {
        let settled = geocal::kinds::tracer_plan::diagnosis::data::dwells_of_file(&cut, keep)
            .expect("read")
            .expect("settled");
        let whole = SettledDwells::of_settled(
            SettledSession::of_session(&read_session(&cut).expect("session")).expect("whole"),
        );
        let whole = match keep {
            WindowSamples::Kept => whole,
            WindowSamples::ArrivalOnly => whole.without_window_samples(),
        };
        assert_eq!(settled, whole);
        assert!(!settled.lengths.measurements.is_empty());
    }
}
