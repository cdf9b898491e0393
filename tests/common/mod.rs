//! Helpers shared by the whole-run tests: comparing estimates with the simulated truth.
#![allow(dead_code)]

use std::path::Path;

use geocal::config::Config;
use geocal::kinds::tracer_plan::run::run;
use geocal::method::multilateration::MultilaterationResults;
use geocal::run::{RunOptions, RunOutput};
use nalgebra::{Matrix3, Rotation3, Vector3};
use serde_json::Value;

pub const DEMO: &str = include_str!("../../config/demo-multilateration.toml");

/// The demo configuration shrunk to 4 stations x 3x3x2 points, so whole runs stay quick.
pub fn small_demo() -> String {
    let cut = DEMO
        .find("[[plan.stations]]\nid = \"s5\"")
        .expect("station s5");
    let sim = DEMO.find("\n[sim]").expect("[sim]");
    format!("{}{}", &DEMO[..cut], &DEMO[sim..])
        .replace("count = 5 }", "count = 3 }")
        .replace("count = 4 }", "count = 2 }")
}

/// The demo shrunk for the diagnosis: all 5 stations, 3x3x3 points, both passes. Fewer
/// lengths than this leave held-out lengths undetermined (cross-validation needs each point
/// seen from 4 stations and each station to keep most of its points when a fold is held out).
pub fn diagnose_demo() -> String {
    DEMO.replace("count = 5 }", "count = 3 }")
        .replace("count = 4 }", "count = 3 }")
}

/// The diagnosis demo with a second reflector `t1` (0.1 m, 0.05 m beside `t0`), measured at
/// every station after `t0`: the plan the points-level `target_offset` test needs.
pub fn two_target_diagnose_demo() -> String {
    let text = diagnose_demo()
        .replace(
            "targets = [{ id = \"t0\", offset_m = [0.0, 0.0, -0.12] }]",
            "targets = [{ id = \"t0\", offset_m = [0.0, 0.0, -0.12] }, { id = \"t1\", offset_m = [0.1, 0.05, -0.12] }]",
        )
        .replace("targets = [\"t0\"]", "targets = [\"t0\", \"t1\"]");
    assert!(text.contains("[\"t0\", \"t1\"]"), "two targets configured");
    text
}

/// Rigid motion (R, t) minimising sum |R a_i + t - b_i|^2 (Kabsch), written independently of
/// the solver's own datum code so that the tests do not grade the solver with itself.
pub fn rigid_fit(a: &[[f64; 3]], b: &[[f64; 3]]) -> (Rotation3<f64>, Vector3<f64>) {
    assert_eq!(a.len(), b.len());
    let n = a.len() as f64;
    let ca = a.iter().map(|p| Vector3::from(*p)).sum::<Vector3<f64>>() / n;
    let cb = b.iter().map(|p| Vector3::from(*p)).sum::<Vector3<f64>>() / n;
    let mut h = Matrix3::zeros();
    for (p, q) in a.iter().zip(b) {
        h += (Vector3::from(*p) - ca) * (Vector3::from(*q) - cb).transpose();
    }
    let svd = h.svd(true, true);
    let (u, v_t) = (svd.u.expect("u"), svd.v_t.expect("v_t"));
    let mut d = Matrix3::identity();
    if (v_t.transpose() * u.transpose()).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = Rotation3::from_matrix_unchecked(v_t.transpose() * d * u.transpose());
    (r, cb - r * ca)
}

/// RMS over points of |R a_i + t - b_i| per coordinate (i.e. sqrt(mean |.|^2 / 3)).
pub fn rms_after(r: &Rotation3<f64>, t: &Vector3<f64>, a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
    let ss: f64 = a
        .iter()
        .zip(b)
        .map(|(p, q)| (r * Vector3::from(*p) + t - Vector3::from(*q)).norm_squared())
        .sum();
    (ss / (3.0 * a.len() as f64)).sqrt()
}

/// The RMS per coordinate that the reported sigmas predict.
pub fn predicted_rms(sigmas: &[[f64; 3]]) -> f64 {
    let ss: f64 = sigmas
        .iter()
        .map(|s| s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
        .sum();
    (ss / (3.0 * sigmas.len() as f64)).sqrt()
}

/// Run the Python checker on a session; fails the test if Python or its packages are missing.
pub fn python_check_session(session: &std::path::Path, expect_tracer_samples: u64) {
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/check_session.py");
    let output = std::process::Command::new("python3")
        .arg(script)
        .arg(session)
        .arg("--expect-tracer-samples")
        .arg(expect_tracer_samples.to_string())
        .output()
        .expect("python3 must be installed to run the independent session reader");
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        output.status.success(),
        "independent reader failed (pip install mcap jsonschema?)\nstdout:\n{stdout}\nstderr:\n{stderr}"
    );
}

pub fn run_with_truth(config_text: &str, dir: &Path) -> (RunOutput, Value) {
    let config = Config::parse(config_text, Path::new("test.toml")).expect("config");
    let truth_path = dir.join("truth.json");
    let output = run(
        &config,
        &RunOptions {
            out_dir: dir.to_path_buf(),
            truth: Some(truth_path.clone()),
            progress: false,
            settings: Default::default(),
            control: Default::default(),
        },
    )
    .expect("run");
    let truth = serde_json::from_slice(&std::fs::read(&truth_path).expect("truth file"))
        .expect("truth json");
    (output, truth)
}

pub fn truth_station<'a>(truth: &'a Value, id: &str) -> &'a Value {
    truth["stations"]
        .as_array()
        .expect("stations")
        .iter()
        .find(|x| x["id"] == id)
        .expect("station in truth")
}

/// The simulated truth of one target's point.
pub fn truth_point<'a>(truth: &'a Value, target: &str, point: usize) -> &'a Value {
    truth["points"]
        .as_array()
        .expect("truth points")
        .iter()
        .find(|t| t["point"] == point && t["target"] == target)
        .expect("truth point")
}

pub fn xyz(v: &Value) -> [f64; 3] {
    [0, 1, 2].map(|k| v[k].as_f64().expect("coordinate"))
}

/// Points and stations within 3x the RMS the reported covariance predicts (after removing a
/// best-fit rigid motion: the datum is a convention), home distances within 4 sigma.
pub fn assert_recovers_truth(results: &MultilaterationResults, truth: &Value) {
    assert!(results.converged, "solver did not converge");
    assert_eq!(
        results.extraction.windows_dropped, 0,
        "{:?}",
        results.extraction.dropped_reasons
    );
    let truth_points: Vec<[f64; 3]> = results
        .points
        .iter()
        .map(|p| xyz(&truth_point(truth, &p.target, p.point)["actual_m"]))
        .collect();
    let estimated: Vec<[f64; 3]> = results.points.iter().map(|p| p.actual_m).collect();
    let (r, t) = rigid_fit(&estimated, &truth_points);
    let point_rms = rms_after(&r, &t, &estimated, &truth_points);
    let point_predicted =
        predicted_rms(&results.points.iter().map(|p| p.sigma_m).collect::<Vec<_>>());
    println!("points: RMS error {point_rms:.3e} m, predicted {point_predicted:.3e} m");
    assert!(
        point_rms <= 3.0 * point_predicted,
        "point RMS {point_rms:e} m exceeds 3x the predicted {point_predicted:e} m"
    );

    let truth_stations: Vec<[f64; 3]> = results
        .stations
        .iter()
        .map(|s| xyz(&truth_station(truth, &s.id)["position_m"]))
        .collect();
    let est_stations: Vec<[f64; 3]> = results.stations.iter().map(|s| s.position_m).collect();
    let station_rms = rms_after(&r, &t, &est_stations, &truth_stations);
    let station_predicted = predicted_rms(
        &results
            .stations
            .iter()
            .map(|s| s.sigma_m)
            .collect::<Vec<_>>(),
    );
    println!("stations: RMS error {station_rms:.3e} m, predicted {station_predicted:.3e} m");
    assert!(
        station_rms <= 3.0 * station_predicted,
        "station RMS {station_rms:e} m exceeds 3x the predicted {station_predicted:e} m"
    );

    // Distances to the homing point do not depend on the datum.
    for s in &results.stations {
        for seg in &s.segments {
            let true_d = truth_station(truth, &s.id)["home_distance_m"][&seg.target]
                .as_f64()
                .expect("true home distance");
            assert!(
                (seg.home_distance_m - true_d).abs() <= 4.0 * seg.sigma_m,
                "station {} target {}: d = {} m, truth {} m, sigma {} m",
                s.id,
                seg.target,
                seg.home_distance_m,
                true_d,
                seg.sigma_m
            );
        }
    }
}

/// A config with unmodelled effects switched on: `effects` is the body of `[sim.effects]`
/// (TOML lines), `seed` replaces the demo's seed. The air temperature swings 0.5 K with a
/// 15 min period (an air-conditioning cycle), so refraction has something to follow.
pub fn with_effects(base: &str, seed: u64, effects: &str) -> String {
    format!(
        "{}\n[sim.environment]\ntemp_swing_k = 0.5\ntemp_period_s = 900.0\n\n[sim.effects]\n{effects}\n",
        base.replace("seed = 20261121", &format!("seed = {seed}"))
    )
}

/// Run a simulated session for `config_text` into `dir`; the recorded file's path.
pub fn record_session(config_text: &str, dir: &Path) -> std::path::PathBuf {
    let config = geocal::config::Config::parse(config_text, std::path::Path::new("effects.toml"))
        .expect("config");
    let output = geocal::kinds::tracer_plan::run::run(
        &config,
        &geocal::run::RunOptions {
            out_dir: dir.to_path_buf(),
            truth: None,
            progress: false,
            settings: Default::default(),
            control: Default::default(),
        },
    )
    .expect("run");
    output.session_path
}

/// Run a simulated session for `config_text` and diagnose the recorded file.
pub fn run_and_diagnose(config_text: &str) -> geocal::diagnose::Diagnosis {
    let dir = tempfile::tempdir().expect("tempdir");
    let session = record_session(config_text, dir.path());
    diagnose_checking_progress(&session)
}

/// Diagnose a session file with a progress hook, and check what it was told: a total fixed
/// from the first call, done never going back, ending at (total, total).
pub fn diagnose_checking_progress(session: &Path) -> geocal::diagnose::Diagnosis {
    let calls = std::sync::Arc::new(std::sync::Mutex::new(Vec::<(u64, u64)>::new()));
    let seen = calls.clone();
    let options = geocal::diagnose::DiagnoseOptions {
        progress: Some(geocal::progress_sink::ProgressSink::new(move |d, t| {
            seen.lock().expect("progress calls").push((d, t))
        })),
        ..Default::default()
    };
    let d = geocal::kinds::diagnosis::diagnose_file(session, &options).expect("diagnose");
    let calls = calls.lock().expect("progress calls");
    let total = calls.first().expect("progress reported").1;
    assert!(total > 1, "{calls:?}");
    assert!(calls.iter().all(|&(_, t)| t == total), "{calls:?}");
    assert!(calls.windows(2).all(|w| w[0].0 < w[1].0), "{calls:?}");
    assert_eq!(calls.last(), Some(&(total, total)), "{calls:?}");
    d
}

/// A geocal-diagnosis/1 object with every field SESSION_FORMAT.md requires.
pub fn assert_diagnosis_format(d: &Value) {
    assert_eq!(d["format"], "geocal-diagnosis/1");
    for key in [
        "noise_floor_m",
        "gap",
        "where",
        "candidates",
        "selected",
        "gap_after",
        "unexplained",
    ] {
        assert!(d.get(key).is_some(), "missing `{key}` in {d}");
    }
}

/// A simulated config's devices swapped for the protocol drivers, fast enough for real time:
/// the HPI-3D tracer at 1000 Hz with its meteo as the environment, a 20 m/s GRBL machine,
/// 30 ms dwells and stillstand windows. Panics if a `sim` device is left (a test bug).
pub fn real_time_devices(config: &str) -> String {
    config
        .replace(
            "id = \"tracer0\"\ndriver = \"sim\"",
            "id = \"tracer0\"\ndriver = \"hpi3d\"",
        )
        .replace("sample_rate_hz = 25.0", "sample_rate_hz = 1000.0")
        .replace(
            "id = \"env0\"\ndriver = \"sim\"\nsample_rate_hz = 1.0",
            "id = \"env0\"\ndriver = \"hpi3d\"\nsample_rate_hz = 4.0",
        )
        .replace(
            "driver = \"sim\"\nfeed_m_s = 0.3",
            "driver = \"grbl\"\nfeed_m_s = 20.0",
        )
        .replace("dwell_s = 2.0", "dwell_s = 0.03")
        .replace("max_dwell_s = 20.0", "max_dwell_s = 2.0")
        .replace("window_s = 0.6", "window_s = 0.03")
}

fn assert_all_replaced(config: &str) {
    assert!(
        !config.contains("\ndriver = \"sim\""),
        "every device replaced:\n{config}"
    );
}

/// The small demo (4 stations x 3x3x2 points, one pass) over the emulators: a 1000 Hz
/// stream, a fast machine and short dwells so the run takes seconds of real time. The
/// stillstand window holds 30 samples; its tolerance stays the demo's.
pub fn hil_config(extra: &str) -> String {
    let text = real_time_devices(&small_demo()).replace(
        "passes = [\"forward\", \"backward\"]",
        "passes = [\"forward\"]",
    );
    assert_all_replaced(&text);
    format!(
        "{text}
[devices.tracer.hpi3d]
ack_timeout_s = 0.05
retries = 3
stream_timeout_s = 0.2
flag_clear_interval_s = 0.05

[devices.machine.grbl]
port = \"\"
ack_timeout_s = 0.3
status_interval_s = 0.005

[hil]
emulate = true
{extra}
"
    )
}

/// A HIL configuration with generous time-outs (2 s for the tracer's stream, 0.5 s for its
/// acks, 2 s for GRBL's `ok` and a Modbus table's answer): for runs that must record no fault at all, so that a loaded
/// machine that stalls an emulator for a while is not taken for a fault. Runs with injected
/// silences keep the short time-outs that detect them.
pub fn generous_timeouts(config: &str) -> String {
    let text = config
        .replace("stream_timeout_s = 0.2", "stream_timeout_s = 2.0")
        .replace("ack_timeout_s = 0.05", "ack_timeout_s = 0.5")
        .replace("ack_timeout_s = 0.3", "ack_timeout_s = 2.0")
        .replace("\ntimeout_s = 0.2", "\ntimeout_s = 2.0");
    assert!(
        text.contains("stream_timeout_s = 2.0") && text.contains("ack_timeout_s = 2.0"),
        "the time-outs to make generous are in the configuration"
    );
    text
}

/// Every fault the HIL emulators inject (`[hil.tracer_faults]`, `[hil.machine_faults]`), for
/// `hil_config`: dropped, corrupted and garbage frames, a silent tracer, a beam break, a lost `ok`.
pub const HIL_FAULTS: &str = "
[hil.tracer_faults]
seed = 7
drop_fraction = 0.002
corrupt_fraction = 0.002
garbage_fraction = 0.002
silence = { from_s = 3.0, to_s = 3.5 }
beam_break = { from_s = 6.0, to_s = 6.3 }

[hil.machine_faults]
drop_ok_at_lines = [20]
";

pub const ROTARY: &str = include_str!("../../config/rotary-tracer.toml");

/// The four-axis setup shrunk for speed: `count` table stations `step_rad` apart (with the
/// extra `[plan.rotary]` lines `plan_lines`) + 1 off the table, 4 x 3 x 2 points, 10 Hz and
/// 1 s dwells.
pub fn reduced_rotary(step_rad: f64, count: usize, plan_lines: &str) -> String {
    let text = ROTARY
        .replace(
            "x = { from = 0.1, to = 0.7, count = 6 }",
            "x = { from = 0.1, to = 0.7, count = 4 }",
        )
        .replace(
            "y = { from = 0.1, to = 0.7, count = 6 }",
            "y = { from = 0.1, to = 0.7, count = 3 }",
        )
        .replace(
            "step_rad = 0.5235987755982988",
            &format!("step_rad = {step_rad:?}\n{plan_lines}"),
        )
        .replace("count = 12", &format!("count = {count}"))
        .replace("sample_rate_hz = 25.0", "sample_rate_hz = 10.0")
        .replace("dwell_s = 2.0", "dwell_s = 1.0")
        .replace("window_s = 0.6", "window_s = 0.4");
    assert!(text.contains(&format!("count = {count}")) && text.contains("dwell_s = 1.0"));
    text
}

/// The four-axis setup shrunk for real time: 4 table stations 90° apart + 1 off the table,
/// 3 x 3 x 2 points, a 1000 Hz stream, a 20 m/s machine, 30 ms dwells and a fast table.
pub fn rotary_base() -> String {
    let text = real_time_devices(ROTARY)
        .replace(
            "x = { from = 0.1, to = 0.7, count = 6 }",
            "x = { from = 0.1, to = 0.7, count = 3 }",
        )
        .replace(
            "y = { from = 0.1, to = 0.7, count = 6 }",
            "y = { from = 0.1, to = 0.7, count = 3 }",
        )
        .replace(
            "step_rad = 0.5235987755982988",
            "step_rad = 1.5707963267948966",
        )
        .replace("count = 12", "count = 4")
        .replace(
            "id = \"c\"\ndriver = \"sim\"",
            "id = \"c\"\ndriver = \"modbus_tcp\"",
        )
        .replace(
            "axis_tilt_rad = 1e-4 }",
            "axis_tilt_rad = 1e-4, speed_rad_s = 20.0, settle_s = 0.05 }",
        );
    assert_all_replaced(&text);
    text
}

/// The driver tables: the HPI-3D at `tracer_port`, GRBL at `machine_port`, the Modbus TCP
/// table with `transport` (a TOML inline table, or empty when emulated in-process).
pub fn driver_tables(tracer_port: &str, machine_port: &str, transport: &str) -> String {
    let transport = if transport.is_empty() {
        String::new()
    } else {
        format!("transport = {transport}\n")
    };
    format!(
        "
[devices.tracer.hpi3d]
port = \"{tracer_port}\"
ack_timeout_s = 0.05
retries = 3
stream_timeout_s = 0.2
flag_clear_interval_s = 0.05

[devices.machine.grbl]
port = \"{machine_port}\"
ack_timeout_s = 0.3
status_interval_s = 0.005

# A table counting 1e-7 rad, 32-bit big-endian words, go/ack/clear handshake. No retries
# inside the driver: every timeout reaches the sequencer, which records and retries it.
[devices.rotary_table.modbus]
{transport}timeout_s = 0.2
retries = 0
ack_timeout_s = 1.0
poll_interval_s = 0.01

[devices.rotary_table.modbus.map]
unit_id = 1
target = {{ address = 100, width_bits = 32, word_order = \"big\", counts_per_rad = 1e7 }}
actual = {{ address = 200, kind = \"input\", width_bits = 32, word_order = \"big\", counts_per_rad = 1e7 }}
status = {{ address = 300, kind = \"input\", in_position_bit = 0, moving_bit = 1, fault_bit = 2 }}
command = {{ address = 110, go_value = 1, clear_value = 0 }}
ack = {{ bit = 3 }}
"
    )
}

/// Everything emulated in-process (`[hil] emulate = true`), with `extra` (fault tables).
pub fn hil_rotary_config(extra: &str) -> String {
    format!(
        "{}{}\n[hil]\nemulate = true\n{extra}\n",
        rotary_base(),
        driver_tables("", "", "")
    )
}

/// `geocal run` (the binary `geocal`) on `example` with each (from, to) edit must fail, and
/// its error must name the file and contain `want` (the key and what was expected).
pub fn assert_run_rejects(geocal: &str, example: &str, cases: &[(&str, &str, &str)]) {
    let dir = tempfile::tempdir().expect("tempdir");
    for &(from, to, want) in cases {
        assert!(example.contains(from), "{from}");
        let path = dir.path().join("bad.toml");
        std::fs::write(&path, example.replacen(from, to, 1)).expect("write");
        let out = std::process::Command::new(geocal)
            .args(["run", path.to_str().expect("utf-8 path"), "--out"])
            .arg(dir.path().join("out"))
            .output()
            .expect("geocal runs");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success());
        assert!(
            stderr.contains(&format!("{}: {want}", path.display())),
            "{to}: {stderr}"
        );
    }
}

/// The (device, message) of every `fault` event with `code`.
pub fn faults<'a>(
    events: &'a [geocal::session::messages::RunEvent],
    code: &str,
) -> Vec<(&'a str, &'a str)> {
    events
        .iter()
        .filter_map(|e| match e {
            geocal::session::messages::RunEvent::Fault {
                device,
                code: c,
                message,
            } if c == code => Some((device.as_str(), message.as_str())),
            _ => None,
        })
        .collect()
}

/// Run the config text of a kind `geocal::kinds` runs (probe_install, hexapod, ...) as
/// `dir/FILE_NAME` with its output in `dir`; the run's output and its truth file.
pub fn run_kind(config_text: &str, dir: &Path, file_name: &str) -> (RunOutput, Value) {
    std::fs::create_dir_all(dir).expect("dir");
    let config = dir.join(file_name);
    std::fs::write(&config, config_text).expect("write config");
    let truth_path = dir.join("truth.json");
    let output = geocal::kinds::run_file(
        &config,
        &RunOptions {
            out_dir: dir.to_path_buf(),
            truth: Some(truth_path.clone()),
            progress: false,
            settings: Default::default(),
            control: Default::default(),
        },
    )
    .expect("run")
    .unwrap_or_else(|| panic!("{file_name}: not a kind geocal::kinds runs"));
    let truth = serde_json::from_slice(&std::fs::read(&truth_path).expect("truth file"))
        .expect("truth json");
    (output, truth)
}

/// The directory a run killed after `cut` messages would leave: `full_dir`'s stored
/// configuration and a session file holding the first `cut` messages of `full_dir`'s
/// session, in `killed_dir`. Returns every raw message of the full session.
pub fn killed_run_dir(
    full_dir: &Path,
    killed_dir: &Path,
    cut: impl FnOnce(&[geocal::session::reader::RawMessage]) -> usize,
) -> (Vec<geocal::session::reader::RawMessage>, usize) {
    use geocal::session::{Recorder, RecorderOptions};
    let (_, messages) = geocal::session::reader::read_session_raw(&full_dir.join("session.mcap"))
        .expect("raw read of the full session");
    let cut = cut(&messages);
    std::fs::create_dir_all(killed_dir).expect("killed dir");
    std::fs::copy(
        full_dir.join("run-config.toml"),
        killed_dir.join("run-config.toml"),
    )
    .expect("the run stores its configuration");
    let recorder = Recorder::create(&killed_dir.join("session.mcap"), RecorderOptions::default())
        .expect("recorder");
    let handle = recorder.handle();
    for m in messages[..cut].iter().cloned() {
        handle.raw(m);
    }
    recorder.finish().expect("finish");
    (messages, cut)
}

/// `geocal run --resume DIR --truth DIR/truth.json` with stdin closed; panics with its stderr
/// unless it succeeds.
pub fn resume_cli(exe: &str, dir: &Path) {
    let out = std::process::Command::new(exe)
        .arg("run")
        .arg("--resume")
        .arg(dir)
        .arg("--truth")
        .arg(dir.join("truth.json"))
        .stdin(std::process::Stdio::null())
        .output()
        .expect("geocal run --resume");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// `session.interrupted-N.mcap` files left in `dir`.
pub fn interrupted_files_left(dir: &Path) -> Vec<std::path::PathBuf> {
    std::fs::read_dir(dir)
        .expect("list dir")
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.to_string_lossy().contains("interrupted"))
        .collect()
}

/// `geocal simulate` in a process of its own: the devices of a machine outside the process
/// under test, with its operator channel. Killed when dropped, even by a failed test.
pub struct Simulated {
    pub child: std::process::Child,
    pub operator_in: std::process::ChildStdin,
    pub operator_out: std::io::BufReader<std::process::ChildStdout>,
    /// The device list simulate printed (`--json`).
    pub listed: Value,
}

impl Simulated {
    /// Host the emulators of the configuration at `config` with the `geocal` binary, writing
    /// the truth to `truth`.
    pub fn start(geocal: &str, config: &Path, truth: &Path) -> Simulated {
        use std::io::BufRead;
        let mut child = std::process::Command::new(geocal)
            .args(["simulate", config.to_str().expect("path"), "--json"])
            .arg("--truth")
            .arg(truth)
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .spawn()
            .expect("start geocal simulate");
        let operator_in = child.stdin.take().expect("stdin");
        let mut operator_out = std::io::BufReader::new(child.stdout.take().expect("stdout"));
        let mut line = String::new();
        operator_out.read_line(&mut line).expect("device list");
        let listed = serde_json::from_str(&line).expect("device JSON");
        Simulated {
            child,
            operator_in,
            operator_out,
            listed,
        }
    }

    /// Where the device of `kind` (tracer, machine, rotary_table) is reached.
    pub fn endpoint(&self, kind: &str) -> String {
        self.listed["devices"]
            .as_array()
            .expect("devices")
            .iter()
            .find(|d| d["kind"] == kind)
            .and_then(|d| d["endpoint"].as_str())
            .unwrap_or_else(|| panic!("no {kind} in {}", self.listed))
            .to_string()
    }

    /// Carry out an operator's `command` (`station <id>`, `target <id>`); simulate's answer.
    pub fn operate(&mut self, command: &str) -> String {
        use std::io::{BufRead, Write};
        writeln!(self.operator_in, "{command}").expect("to simulate");
        let mut reply = String::new();
        self.operator_out
            .read_line(&mut reply)
            .expect("simulate reply");
        reply.trim().to_owned()
    }
}

impl Drop for Simulated {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Whether the real LinuxCNC can run here; without it the caller skips, saying why, except
/// in CI, which must run the LinuxCNC tests and fails instead.
pub fn linuxcnc_available() -> bool {
    match geocal::sim::linuxcnc::unavailable() {
        None => true,
        Some(why) if std::env::var_os("CI").is_some() => {
            panic!("CI must run the LinuxCNC tests, but {why}")
        }
        Some(why) => {
            eprintln!("skipping the LinuxCNC tests: {why}");
            false
        }
    }
}

/// The smallest grid of the small demo's that the 21-error decomposition takes (at most half
/// as many unknowns as equations: 5 x 4 x 3 positions, 60 points).
pub fn verification_grid(text: String) -> String {
    let text = text
        .replace(
            "x = { from = 0.1, to = 1.3, count = 3 }",
            "x = { from = 0.1, to = 1.3, count = 5 }",
        )
        .replace(
            "y = { from = 0.2, to = 2.2, count = 3 }",
            "y = { from = 0.2, to = 2.2, count = 4 }",
        )
        .replace(
            "z = { from = 0.15, to = 0.95, count = 2 }",
            "z = { from = 0.15, to = 0.95, count = 3 }",
        );
    assert!(
        text.contains("count = 5 }") && text.contains("count = 4 }"),
        "grid set"
    );
    text
}

/// A verification run's positioning error of one axis against the pass rule.
pub struct PassRule {
    pub rms_before_m: f64,
    pub rms_after_m: f64,
    /// RMS of the before and after σ combined at each position.
    pub rms_sigma_m: f64,
    /// 2·RMS(σ) + the tables' interpolation error: the documented rule a report applies.
    pub bound_m: f64,
    /// The bound a real-time test asserts: `REAL_TIME_SIGMAS`·RMS(σ) + interpolation error.
    pub real_time_bound_m: f64,
}

/// Multiple of RMS(σ) a real-time verification test allows. A real-time run's noise draws
/// change with the scheduling (how many samples each window holds), so the test meets a new
/// draw on every run, and the documented 2σ rule on a curve of 2–4 non-datum values fails a
/// correct compensation by chance in ~0.3–2 % of runs per axis. Values along a curve are
/// correlated through the datum; in the worst case (one common error) RMS/RMS(σ) is |N(0,1)|,
/// and P(|z| > 3.89) = 1e-4: at most one false failure in 10 000 runs per axis, while a
/// table with a wrong sign or none at all still leaves 50–140 RMS(σ).
pub const REAL_TIME_SIGMAS: f64 = 3.89;

/// Axis `k`'s positioning error before and after compensation against the pass rule
/// RMS(after) ≤ 2·RMS(σ) + interpolation error (docs/compensation.md).
pub fn pass_rule(
    before: &geocal::compensate::Calibration,
    after: &geocal::compensate::Calibration,
    k: usize,
    interpolation_m: f64,
) -> PassRule {
    let positioning = |cal: &geocal::compensate::Calibration| {
        let c = cal.positioning(k).expect("positioning");
        let values: Vec<f64> = c.values.iter().map(|v| v.expect("value")).collect();
        let sigma: Vec<f64> = c.sigma.iter().map(|s| s.unwrap_or(0.0)).collect();
        (values, sigma)
    };
    let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt();
    let (vb, sb) = positioning(before);
    let (va, sa) = positioning(after);
    let sigma: Vec<f64> = sb.iter().zip(&sa).map(|(b, a)| b.hypot(*a)).collect();
    let rms_sigma_m = rms(&sigma);
    PassRule {
        rms_before_m: rms(&vb),
        rms_after_m: rms(&va),
        rms_sigma_m,
        bound_m: 2.0 * rms_sigma_m + interpolation_m,
        real_time_bound_m: REAL_TIME_SIGMAS * rms_sigma_m + interpolation_m,
    }
}

/// The addresses `geocal serve` prints on its first line of stdout (piped): the API's
/// `http://…` URL and, when the live view is on, its `ws://…` URL.
pub fn daemon_banner(child: &mut std::process::Child) -> (String, Option<String>) {
    use std::io::BufRead;
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().expect("stdout"))
        .read_line(&mut line)
        .expect("the daemon's first line");
    let url = line
        .split_whitespace()
        .find(|w| w.starts_with("http://"))
        .unwrap_or_else(|| panic!("no address in {line:?}"))
        .trim_end_matches(',')
        .to_owned();
    let live = line
        .split_whitespace()
        .find(|w| w.starts_with("ws://"))
        .map(str::to_owned);
    (url, live)
}

/// The daemon's heap in use, bytes (`geocal_heap_in_use_bytes` in its `/metrics`).
pub fn heap_in_use_bytes(client: &reqwest::blocking::Client, url: &str) -> u64 {
    let metrics = client
        .get(format!("{url}/metrics"))
        .send()
        .expect("GET /metrics")
        .text()
        .expect("metrics text");
    metrics
        .lines()
        .find_map(|l| l.strip_prefix("geocal_heap_in_use_bytes "))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no heap metric in {metrics}"))
}

/// A verification's first half: the small demo on the verification grid, one pass,
/// calibrated in virtual time under `dir/before`, and each axis's table exported in its
/// format into `dir/tables/SUB/`. Returns the calibration, each axis's interpolation error
/// and the export's files per listed axis.
pub fn calibrate_and_export(
    dir: &Path,
    axes: &[(usize, geocal::compensate::TableFormat, &str)],
) -> (
    geocal::compensate::Calibration,
    [f64; 3],
    Vec<Vec<geocal::compensate::OutputFile>>,
) {
    use geocal::compensate::{export, Calibration, ExportOptions};
    let (before, _) = run_with_truth(&one_pass_verification(small_demo()), &dir.join("before"));
    let cal = Calibration::load(&before.results_path).expect("results");
    let mut interp = [0.0; 3];
    let mut files = Vec::new();
    for &(k, format, sub) in axes {
        let options = ExportOptions {
            axes: vec![k],
            ..Default::default()
        };
        let e = export(&cal, format, &options, &Default::default()).expect("export");
        interp[k] = e.steps[0].interpolation_error_m;
        let folder = dir.join("tables").join(sub);
        std::fs::create_dir_all(&folder).expect("dir");
        for f in &e.files {
            std::fs::write(folder.join(&f.name), &f.text).expect("write");
        }
        files.push(e.files);
    }
    (cal, interp, files)
}

/// A configuration on the verification grid with one forward pass.
pub fn one_pass_verification(text: String) -> String {
    verification_grid(text.replace(
        "passes = [\"forward\", \"backward\"]",
        "passes = [\"forward\"]",
    ))
}

/// Whether Python can import `module` (from the pip package `package`). Without it the test
/// is skipped with a line, unless `CI` is set: CI installs it, so its absence is a failure.
pub fn python_module_available(module: &str, package: &str) -> bool {
    let found = std::process::Command::new("python3")
        .args(["-c", &format!("import {module}")])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !found {
        assert!(
            std::env::var_os("CI").is_none(),
            "{module} is not importable (pip install {package}), and CI is set"
        );
        println!("skipped: {module} is not importable (pip install {package})");
    }
    found
}

/// A machine target at (x, y, z), m.
pub fn target(x: f64, y: f64, z: f64) -> geocal_drivers::AxisPositions {
    [("x", x), ("y", y), ("z", z)]
        .into_iter()
        .map(|(a, v)| (a.to_string(), v))
        .collect()
}

/// Poll the machine until Idle (or an error), at most `limit`.
pub async fn wait_idle(
    m: &mut impl geocal_drivers::Machine,
    limit: std::time::Duration,
) -> Result<geocal_drivers::AxisPositions, geocal_drivers::DeviceError> {
    let t0 = tokio::time::Instant::now();
    loop {
        if let geocal_drivers::MachineState::Idle { position } = m.state().await? {
            return Ok(position);
        }
        assert!(t0.elapsed() < limit, "no arrival within {limit:?}");
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
}
