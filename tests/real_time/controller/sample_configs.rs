//! The LinuxCNC driver against LinuxCNC started from the sample configurations Debian ships
//! (`/usr/share/doc/linuxcnc/examples/sample-configs/sim/axis/`), copied with only `[DISPLAY]
//! DISPLAY = linuxcncrsh` changed (and `[EMCMOT] COMM_TIMEOUT` raised for a computer without
//! realtime, `LinuxCnc::start_config`), as a machine shop's LinuxCNC would be found rather than as
//! geocal writes it: the metric mill with home switches (`axis_mm.ini`), the inch mill
//! (`axis.ini`) and the gantry with 4 joints XYYZ (`gantry/gantry_mm.ini`). One LinuxCNC start
//! per configuration. The operator is another linuxcncrsh client, as a pendant or the AXIS GUI
//! would be. Skips without LinuxCNC or root (saying why), fails when `CI` is set.

use crate::common;

use common::{target, wait_idle};

use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::time::Duration;

use geocal::sim::linuxcnc::LinuxCnc;
use geocal_drivers::linuxcnc::{
    HomePolicy, LinuxCncConfig, LinuxCncMachine, MoveMode, StreamConnector, ALARM_ESTOP,
};
use geocal_drivers::{AxisPositions, DeviceError, Machine, MachineState};

const SAMPLES: &str = "/usr/share/doc/linuxcnc/examples/sample-configs/sim/axis";

/// A shipped sample configuration, or None (skip, saying why; CI fails in
/// `linuxcnc_available` already when LinuxCNC is missing).
fn sample(relative: &str) -> Option<PathBuf> {
    if !common::linuxcnc_available() {
        return None;
    }
    let path = Path::new(SAMPLES).join(relative);
    if path.is_file() {
        return Some(path);
    }
    assert!(
        std::env::var_os("CI").is_none(),
        "CI must run the sample-config tests, but {} is missing",
        path.display()
    );
    eprintln!("skipping: {} is missing", path.display());
    None
}

/// Start LinuxCNC from `ini`, run `exercise` on a current-thread runtime, shut LinuxCNC
/// down; LinuxCNC's log is printed when the exercise panics.
fn with_linuxcnc(ini: &Path, exercise: impl AsyncFnOnce(&LinuxCnc)) {
    with_linuxcnc_blocking(ini, |lcnc| {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .expect("runtime");
        rt.block_on(exercise(lcnc))
    })
}

/// Start LinuxCNC from `ini`, run `exercise`, shut LinuxCNC down; LinuxCNC's log is printed
/// when the exercise panics.
fn with_linuxcnc_blocking(ini: &Path, exercise: impl FnOnce(&LinuxCnc)) {
    let started = std::time::Instant::now();
    let lcnc = LinuxCnc::start_config(ini, Duration::from_secs(180)).expect("LinuxCNC starts");
    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| exercise(&lcnc)));
    let log = lcnc.log_tail(40);
    lcnc.shutdown().expect("clean shutdown");
    println!(
        "{}: {:.1} s",
        ini.display(),
        started.elapsed().as_secs_f64()
    );
    if let Err(panic) = outcome {
        eprintln!("LinuxCNC's log:\n{log}");
        std::panic::resume_unwind(panic);
    }
}

fn connector(lcnc: &LinuxCnc) -> StreamConnector {
    let ns = lcnc.connector().expect("namespace connector");
    std::sync::Arc::new(move || {
        let ns = ns.clone();
        Box::pin(async move {
            let stream = tokio::task::spawn_blocking(move || ns.connect())
                .await
                .map_err(std::io::Error::other)??;
            stream.set_nonblocking(true)?;
            tokio::net::TcpStream::from_std(stream)
        })
    })
}

fn config(home: HomePolicy, power_on: bool) -> LinuxCncConfig {
    LinuxCncConfig {
        id: "mill".into(),
        home,
        power_on,
        motion: MoveMode::Rapid,
        reply_timeout_s: 30.0,
        reconnect_timeout_s: 10.0,
        ..LinuxCncConfig::default()
    }
}

/// Move to each target in turn; each must arrive within `tolerance_m`.
async fn visit(m: &mut LinuxCncMachine, targets: &[AxisPositions], tolerance_m: f64) {
    for t in targets {
        m.start_move(t).await.expect("move accepted");
        let at = wait_idle(m, Duration::from_secs(60))
            .await
            .expect("arrives");
        for (axis, want) in t {
            assert!(
                (at[axis] - want).abs() <= tolerance_m,
                "{axis}: at {}, commanded {want}",
                at[axis]
            );
        }
    }
}

/// Another linuxcncrsh client: the operator at a pendant or the AXIS GUI.
struct Operator {
    stream: TcpStream,
    reader: BufReader<TcpStream>,
}

impl Operator {
    /// Connected with control taken (`set enable`), as a GUI holds it.
    fn connect(lcnc: &LinuxCnc) -> Operator {
        let stream = lcnc.connect().expect("operator connects");
        stream
            .set_read_timeout(Some(Duration::from_secs(30)))
            .expect("timeout");
        let reader = BufReader::new(stream.try_clone().expect("clone"));
        let mut op = Operator { stream, reader };
        for line in [
            "hello EMC operator 1.0",
            "set verbose on",
            "set enable EMCTOO",
        ] {
            op.send(line);
        }
        op
    }

    /// The reply to `line` (its echo skipped).
    fn ask(&mut self, line: &str) -> String {
        self.stream
            .write_all(format!("{line}\r\n").as_bytes())
            .expect("write");
        loop {
            let mut reply = String::new();
            let n = self.reader.read_line(&mut reply).expect("reply");
            assert!(n > 0, "{line}: linuxcncrsh closed the connection");
            let reply = reply.trim();
            if !reply.is_empty() && !reply.eq_ignore_ascii_case(line) {
                return reply.to_string();
            }
        }
    }

    /// A `set` that must be acknowledged.
    fn send(&mut self, line: &str) {
        let reply = self.ask(line);
        assert!(
            reply.contains("ACK") && !reply.contains("NAK"),
            "{line}: {reply}"
        );
    }

    /// The value of `get <key>` (without the key).
    fn get(&mut self, key: &str) -> String {
        let reply = self.ask(&format!("get {key}"));
        let (k, value) = reply.split_once(' ').unwrap_or((&reply, ""));
        assert!(k.eq_ignore_ascii_case(key), "get {key}: {reply}");
        value.trim().to_string()
    }

    /// E-stop, machine power, mode and every modal code of the interpreter (the motion mode
    /// first, the feed rate last), as one comparable line.
    fn controller_state(&mut self) -> String {
        format!(
            "estop {} machine {} mode {} codes {}",
            self.get("estop"),
            self.get("machine"),
            self.get("mode"),
            self.get("program_codes")
        )
    }

    /// Wait until `get key` answers `want` (LinuxCNC's status follows a `set` within cycles).
    fn wait_for(&mut self, key: &str, want: &str) {
        for _ in 0..500 {
            if self.get(key).eq_ignore_ascii_case(want) {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        panic!("get {key} never answered {want}");
    }

    /// Home all joints and wait until the first `joints` report homed.
    fn home_all(&mut self, joints: usize) {
        self.send("set mode manual");
        self.send("set home -1");
        for _ in 0..1500 {
            let flags = self.get("joint_homed");
            if flags.split_whitespace().take(joints).all(|f| f == "YES") {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        panic!("homing did not finish");
    }
}

/// The metric mill with home switches: refusals leave it exactly as found; an E-stop pressed
/// by the operator in the middle of a run stops it (LinuxCNC stays in E-stop, geocal sends
/// nothing that would release it); once the operator cleared it, a new connection (as
/// `geocal run --resume` opens) finishes the moves.
pub fn axis_mm_estop_stops_the_run_and_refusals_change_nothing() {
    let Some(ini) = sample("axis_mm.ini") else {
        return;
    };
    with_linuxcnc(&ini, async |lcnc| {
        let mut op = Operator::connect(lcnc);
        let fresh = op.controller_state();
        assert!(fresh.starts_with("estop ON machine OFF"), "{fresh}");
        // home = "refuse" with unhomed joints: refused although power_on allows powering on.
        let e = LinuxCncMachine::connect_with(config(HomePolicy::Refuse, true), connector(lcnc))
            .await
            .err()
            .expect("unhomed machine refused");
        assert!(e.to_string().contains("not homed"), "{e}");
        assert_eq!(
            op.controller_state(),
            fresh,
            "refusal changed the controller"
        );
        // In E-stop without power_on: refused, nothing changed.
        let e = LinuxCncMachine::connect_with(config(HomePolicy::Allow, false), connector(lcnc))
            .await
            .err()
            .expect("E-stop refused without power_on");
        let text = e.to_string();
        assert!(
            text.contains("in E-stop") && text.contains("power_on = true"),
            "{text}"
        );
        assert_eq!(
            op.controller_state(),
            fresh,
            "refusal changed the controller"
        );

        // power_on and home allowed: geocal powers on and homes (home switches), then runs.
        let mut m = LinuxCncMachine::connect_with(config(HomePolicy::Allow, true), connector(lcnc))
            .await
            .expect("connects, powers on, homes");
        let plan = [
            target(0.010, 0.005, 0.002),
            target(0.030, -0.010, 0.010),
            target(-0.030, 0.020, -0.005),
            target(0.0, 0.0, 0.0),
        ];
        visit(&mut m, &plan[..1], 1e-6).await;
        // The operator presses E-stop in the middle of the next move.
        m.start_move(&plan[1]).await.expect("move accepted");
        tokio::time::sleep(Duration::from_millis(300)).await;
        assert_eq!(m.state().await.expect("moving"), MachineState::Moving);
        // One linuxcncrsh client has control at a time: the operator takes it, as a GUI does.
        op.send("set enable EMCTOO");
        op.send("set estop on");
        let e = wait_idle(&mut m, Duration::from_secs(30))
            .await
            .expect_err("the E-stop stops the move");
        assert!(
            matches!(
                e,
                DeviceError::Alarm {
                    code: ALARM_ESTOP,
                    ..
                }
            ) && e.to_string().contains("not by geocal"),
            "named as an E-stop once settled: {e}"
        );
        let requests = m.requests();
        let e = m.unlock().await.expect_err("geocal does not release it");
        assert!(e.to_string().contains("--resume"), "{e}");
        let stopped_at = op.get("abs_act_pos");
        std::thread::sleep(Duration::from_millis(1500));
        let state = op.controller_state();
        assert!(state.starts_with("estop ON machine OFF"), "{state}");
        assert_eq!(op.get("abs_act_pos"), stopped_at, "nothing moved");
        // What `unlock` asked: queries only (estop, machine and their settling).
        println!(
            "unlock sent {} queries and no command",
            m.requests() - requests
        );
        // The run ends (its `finish`): in E-stop LinuxCNC refuses mode changes; it says so.
        let e = m
            .finish()
            .await
            .expect_err("nothing can be set back in E-stop");
        assert!(e.to_string().contains("E-stop"), "{e}");
        assert!(op.controller_state().starts_with("estop ON machine OFF"));
        drop(m);

        // The operator clears it at the machine; the resumed run connects without power_on.
        op.send("set estop off");
        op.send("set machine on");
        op.wait_for("machine", "ON");
        let mut m =
            LinuxCncMachine::connect_with(config(HomePolicy::Allow, false), connector(lcnc))
                .await
                .expect("the resumed run connects");
        visit(&mut m, &plan[1..], 1e-6).await;
        m.finish().await.expect("finish");
    });
}

/// The inch mill, found in G20 with the operator's G91 and in manual mode: geocal's moves
/// arrive (positions in inches converted), and afterwards LinuxCNC is in G20, G91 and manual
/// mode again.
pub fn axis_inch_machine_ends_in_g20_with_its_modes() {
    let Some(ini) = sample("axis.ini") else {
        return;
    };
    with_linuxcnc(&ini, async |lcnc| {
        let mut op = Operator::connect(lcnc);
        op.send("set estop off");
        op.send("set machine on");
        op.wait_for("machine", "ON");
        op.home_all(3);
        op.send("set mode mdi");
        op.wait_for("mode", "MDI");
        op.send("set mdi G91");
        op.send("set mode manual");
        op.wait_for("mode", "MANUAL");
        let found = op.controller_state();
        assert!(
            found.contains(" G20 ") && found.contains(" G91 ") && found.contains("mode MANUAL"),
            "{found}"
        );
        let mut m =
            LinuxCncMachine::connect_with(config(HomePolicy::Refuse, false), connector(lcnc))
                .await
                .expect("connects");
        assert_eq!(m.mm_per_unit(), 25.4);
        // linuxcncrsh reports inches with 6 decimals: 25.4 nm.
        visit(
            &mut m,
            &[
                target(0.0254, -0.0127, -0.01),
                target(-0.05, 0.03, -0.02),
                target(0.0, 0.0, 0.0),
            ],
            13e-9,
        )
        .await;
        m.finish().await.expect("finish");
        assert_eq!(op.controller_state(), found, "left as found");
    });
}

/// The gantry (4 joints XYYZ): the driver reads the joint count from LinuxCNC's INI (4;
/// linuxcncrsh itself reports six), refuses with `home = "refuse"` naming all four joints,
/// homes all four with `allow`, and moves; both Y joints follow the Y axis.
pub fn gantry_runs_with_its_four_joints() {
    let Some(ini) = sample("gantry/gantry_mm.ini") else {
        return;
    };
    with_linuxcnc(&ini, async |lcnc| {
        let mut op = Operator::connect(lcnc);
        assert_eq!(op.get("joint_homed"), "NO NO NO NO NO NO");
        let e = LinuxCncMachine::connect_with(config(HomePolicy::Refuse, true), connector(lcnc))
            .await
            .err()
            .expect("unhomed gantry refused");
        assert!(e.to_string().contains("[0, 1, 2, 3] are not homed"), "{e}");
        let mut m = LinuxCncMachine::connect_with(config(HomePolicy::Allow, true), connector(lcnc))
            .await
            .expect("connects, homes 4 joints");
        let homed = op.get("joint_homed");
        assert!(homed.starts_with("YES YES YES YES"), "{homed}");
        let t = target(0.040, 0.030, 0.090);
        visit(&mut m, std::slice::from_ref(&t), 1e-6).await;
        let joints: Vec<f64> = op
            .get("joint_pos")
            .split_whitespace()
            .map(|v| v.parse().expect("number"))
            .collect();
        // Joint 0 is X, joints 1 and 2 the two sides of Y (mm).
        assert!((joints[0] - 40.0).abs() < 1e-5, "{joints:?}");
        assert!((joints[1] - 30.0).abs() < 1e-5, "{joints:?}");
        assert!((joints[2] - 30.0).abs() < 1e-5, "{joints:?}");
        m.finish().await.expect("finish");
    });
}

/// The whole-run tests' plan on `axis_mm`: 4 stations x 16 points 5 mm apart around the
/// homed position (multilateration's minimum of 16), the HPI-3D tracer at `port`, LinuxCNC's
/// linuxcncrsh at 127.0.0.1 (geocal runs in its namespace) with the driver's defaults:
/// no `power_on`, `home = "refuse"`: the operator powered the machine on and homed it.
fn whole_run_config(port: &str) -> String {
    format!(
        r#"kind = "multilateration"

[machine]
name = "axis_mm sample config (simulated steel)"
structure = "FYXZ"
travel_m = {{ x = [-0.02, 0.05], y = [-0.02, 0.03], z = [-0.03, 0.02] }}
targets = [{{ id = "t0", offset_m = [0.0, 0.0, -0.05] }}]

[devices.tracer]
id = "tracer0"
driver = "hpi3d"
noise_m = 1.0e-7
noise_ppm = 0.2
sample_rate_hz = 500.0
dead_path_m = 0.0
compensated = true

[devices.tracer.hpi3d]
port = "{port}"
ack_timeout_s = 0.5
stream_timeout_s = 2.0

[devices.machine]
id = "mill"
driver = "linuxcnc"
feed_m_s = 0.03

[devices.machine.linuxcnc]
host = "127.0.0.1"
motion = "rapid"
status_interval_s = 0.01
reply_timeout_s = 30.0
stall_timeout_s = 30.0

[plan]
targets = ["t0"]
passes = ["forward"]
dwell_s = 0.03
max_dwell_s = 2.0
stillstand = {{ window_s = 0.03, tolerance_m = 5e-6 }}

[plan.grid]
x = {{ from = 0.0, to = 0.015, count = 4 }}
y = {{ from = 0.0, to = 0.005, count = 2 }}
z = {{ from = -0.005, to = 0.0, count = 2 }}
order = "serpentine"

[[plan.stations]]
id = "s1"
hint_m = [-0.10, -0.08, -0.12]
[[plan.stations]]
id = "s2"
hint_m = [0.13, -0.07, -0.06]
[[plan.stations]]
id = "s3"
hint_m = [0.12, 0.10, -0.15]
[[plan.stations]]
id = "s4"
hint_m = [-0.09, 0.11, -0.04]
"#
    )
}

/// The world of the whole-run tests: the plan's truth, with the steel following LinuxCNC's
/// commanded joints.
const WORLD: &str = r#"
[sim]
seed = 32
station_hint_error_m = 0.003
relocation_s = 0.0
"#;

/// The world's carriages at LinuxCNC's commanded joint positions (`joint.N.pos-cmd`, mm):
/// the sample config's home offsets are in `motor-pos-cmd`, not in these.
struct CommandedJoints {
    reader: std::sync::Mutex<geocal::sim::linuxcnc::HalReader>,
    last_m: std::sync::Mutex<[f64; 3]>,
}

impl geocal::sim::world::JointSource for CommandedJoints {
    fn joints_m(&self) -> [f64; 3] {
        let mut last = self.last_m.lock().unwrap_or_else(|e| e.into_inner());
        let read = self.reader.lock().unwrap_or_else(|e| e.into_inner()).read();
        if let Ok(mm) = read {
            if mm.len() == 3 {
                *last = [mm[0] * 1e-3, mm[1] * 1e-3, mm[2] * 1e-3];
            }
        }
        *last
    }
}

/// The simulated tracer of the whole-run tests, as in the real-controller HIL: the HPI-3D
/// emulator on a pty, measuring a simulated world whose carriages follow LinuxCNC. A fresh
/// emulator for each run (as the HIL hosts one per run), reached through one link path.
struct TracerRig {
    runtime: tokio::runtime::Runtime,
    emulator: Option<geocal_drivers::hpi3d::Hpi3dEmulator>,
    host_end: Option<geocal_drivers::serial::SerialStream>,
    world: geocal::sim::devices::SharedWorld,
    time: std::sync::Arc<geocal::sim::hil::HilTime>,
    noise: geocal::extract::NoiseModel,
    rate_hz: f64,
    /// Holds the link path; removed with the rig.
    _links: tempfile::TempDir,
    port: String,
}

impl TracerRig {
    fn start(lcnc: &LinuxCnc) -> TracerRig {
        use std::sync::{Arc, Mutex};
        let text = format!("{}{WORLD}", whole_run_config("pty"));
        let config = geocal::config::Config::parse(&text, Path::new("world.toml")).expect("config");
        let plan = geocal::plan::Plan::from_config(&config);
        let epoch_ns = geocal::clock::system_now_ns();
        let time = Arc::new(geocal::sim::hil::HilTime::new(epoch_ns));
        let mut world = geocal::sim::world::SimWorld::new(
            &config,
            &plan,
            Arc::new(geocal::clock::VirtualClock::new(epoch_ns)),
        )
        .expect("world");
        let pins = (0..3).map(|j| format!("joint.{j}.pos-cmd")).collect();
        world.follow_joints(Box::new(CommandedJoints {
            reader: Mutex::new(lcnc.hal_reader(pins).expect("HAL reader")),
            last_m: Mutex::new([0.0; 3]),
        }));
        let links = tempfile::tempdir().expect("link dir");
        let port = links.path().join("hpi3d").display().to_string();
        let mut rig = TracerRig {
            runtime: tokio::runtime::Builder::new_multi_thread()
                .worker_threads(1)
                .enable_all()
                .build()
                .expect("runtime"),
            emulator: None,
            host_end: None,
            world: Arc::new(Mutex::new(world)),
            time,
            noise: config.devices.tracer.noise_model(),
            rate_hz: config.devices.tracer.sample_rate_hz,
            _links: links,
            port,
        };
        rig.fresh_emulator(1);
        rig
    }

    /// A new emulator on a new pty behind the link path (the old one stopped).
    fn fresh_emulator(&mut self, seed: u64) {
        drop(self.emulator.take());
        drop(self.host_end.take());
        let source = geocal::sim::hil::WorldTracerSource::new(
            self.world.clone(),
            self.time.clone(),
            self.noise,
            seed,
        );
        let _entered = self.runtime.enter();
        let (emulator, host_end) = geocal_drivers::hpi3d::Hpi3dEmulator::spawn_pty(
            geocal_drivers::hpi3d::EmulatorConfig {
                rate_hz: self.rate_hz,
                ..Default::default()
            },
            Box::new(source),
        )
        .expect("HPI-3D emulator");
        let _ = std::fs::remove_file(&self.port);
        std::os::unix::fs::symlink(emulator.slave_path().expect("pty path"), &self.port)
            .expect("link");
        self.emulator = Some(emulator);
        self.host_end = Some(host_end);
    }

    /// What a run in LinuxCNC's namespace is given: the operator places the tracer in the
    /// world, progress goes to `progress`, `cancel` cancels it.
    fn options(
        &self,
        dir: &Path,
        progress: std::sync::mpsc::Sender<u64>,
        cancel: tokio_util::sync::CancellationToken,
    ) -> geocal::run::RunOptions {
        let (world, time) = (self.world.clone(), self.time.clone());
        let progress = std::sync::Mutex::new(progress);
        geocal::run::RunOptions {
            out_dir: dir.to_path_buf(),
            truth: None,
            progress: false,
            settings: Default::default(),
            control: geocal::run::control::RunControl {
                cancel,
                progress: Some(geocal::progress_sink::ProgressSink::new(move |done, _| {
                    let _ = progress.lock().map(|tx| tx.send(done));
                })),
                operator: Some(std::sync::Arc::new(move || {
                    Box::new(geocal::sim::hil::HilOperator {
                        world: world.clone(),
                        time: time.clone(),
                    }) as Box<dyn geocal_drivers::Operator>
                })),
                ..Default::default()
            },
        }
    }
}

impl Drop for TracerRig {
    fn drop(&mut self) {
        // The emulator's task holds the world and its HAL reader: gone before LinuxCNC is.
        drop(self.emulator.take());
        let runtime = std::mem::replace(
            &mut self.runtime,
            tokio::runtime::Builder::new_current_thread()
                .build()
                .expect("runtime"),
        );
        runtime.shutdown_timeout(Duration::from_secs(5));
    }
}

/// A whole run (`geocal run CONFIG` or `--resume DIR`, as the CLI calls them) on a thread
/// inside LinuxCNC's namespace.
type RunThread = std::thread::JoinHandle<std::io::Result<Result<String, String>>>;

fn spawn_run(
    lcnc: &LinuxCnc,
    config_text: &str,
    options: geocal::run::RunOptions,
    resume: bool,
) -> RunThread {
    let config_path = options.out_dir.join("whole-run.toml");
    std::fs::create_dir_all(&options.out_dir).expect("run dir");
    std::fs::write(&config_path, config_text).expect("config file");
    let connector = lcnc.connector().expect("namespace");
    connector
        .spawn_inside(move || {
            let dir = options.out_dir.clone();
            let output = if resume {
                geocal::kinds::kind_of_run_dir(&dir, None)
                    .and_then(|kind| kind.resume(&dir, None, &options))
            } else {
                geocal::kinds::kind_of_config(&config_path).and_then(|kind| {
                    kind.run(&config_path, &options, &geocal::kinds::RunFlags::default())
                })
            };
            output.map(|o| o.recorded).map_err(|e| format!("{e:#}"))
        })
        .expect("a thread in LinuxCNC's namespace")
}

/// Wait until the run reports `points` done (generous: a loaded machine).
fn wait_for_progress(progress: &std::sync::mpsc::Receiver<u64>, points: u64) {
    loop {
        match progress.recv_timeout(Duration::from_secs(120)) {
            Ok(done) if done >= points => return,
            Ok(_) => {}
            Err(e) => panic!("the run did not reach point {points}: {e}"),
        }
    }
}

fn run_events(
    session: &geocal::session::reader::Session,
) -> Vec<geocal::session::messages::RunEvent> {
    session.events.iter().map(|e| e.msg.clone()).collect()
}

/// No sample lost from any measurement: inside every point's window (`point_begin` to
/// `point_end`) the tracer's seq runs without a gap, and at most `runs` streams (a resumed
/// run starts a new one). Frames lost outside the windows are printed: a resumed run's
/// preparation (copying the stopped session) does not read the tracer, and this emulator,
/// like a real device, streams on meanwhile.
fn assert_tracer_windows_whole(session: &geocal::session::reader::Session, runs: usize) {
    use geocal::session::messages::RunEvent;
    let samples = &session.tracers["tracer0"];
    assert!(!samples.is_empty(), "tracer samples recorded");
    let mut windows = Vec::new();
    let mut begun = None;
    for e in &session.events {
        match e.msg {
            RunEvent::PointBegin { .. } => begun = Some(e.log_time_ns),
            RunEvent::PointEnd { .. } => windows.extend(begun.take().map(|b| (b, e.log_time_ns))),
            _ => {}
        }
    }
    let mut restarts = 0;
    for pair in samples.windows(2) {
        let (a, b) = (&pair[0], &pair[1]);
        if b.msg.seq == a.msg.seq + 1 {
            continue;
        }
        if b.msg.seq < a.msg.seq {
            restarts += 1;
            continue;
        }
        let inside = windows
            .iter()
            .any(|&(from, to)| from <= b.log_time_ns && a.log_time_ns <= to);
        assert!(
            !inside,
            "tracer seq jumps from {} to {} inside a point's window: samples lost",
            a.msg.seq, b.msg.seq
        );
        println!(
            "outside every window: tracer seq jumps from {} to {}",
            a.msg.seq, b.msg.seq
        );
    }
    assert!(restarts < runs, "{restarts} restarts of the tracer stream");
}

/// A whole `geocal run` against LinuxCNC started from Debian's `axis_mm` (the operator powered
/// it on and homed it; geocal's defaults: no `power_on`, `home = "refuse"`): the operator
/// presses E-stop from another linuxcncrsh client at point 6 → the run stops with the session
/// kept and the E-stop recorded as one alarm; LinuxCNC stays in E-stop and its commanded
/// position does not change from the moment the E-stop shows until seconds after the run
/// ended; no point is begun after the alarm. The operator clears it (`set estop off`, `set
/// machine on`, homing if lost), and `geocal run --resume` completes: every planned point,
/// every message of the stopped session unchanged, no tracer sample lost from any point's
/// window.
pub fn axis_mm_whole_run_stopped_by_an_estop_resumes_with_nothing_lost() {
    use geocal::session::messages::RunEvent;
    use geocal::session::reader::{read_session, read_session_raw};
    let Some(ini) = sample("axis_mm.ini") else {
        return;
    };
    with_linuxcnc_blocking(&ini, |lcnc| {
        let mut op = Operator::connect(lcnc);
        op.send("set estop off");
        op.send("set machine on");
        op.wait_for("machine", "ON");
        op.home_all(3);
        let mut rig = TracerRig::start(lcnc);
        let config_text = whole_run_config(&rig.port);
        let dir = tempfile::tempdir().expect("tempdir");
        let started = std::time::Instant::now();

        let (tx, progress) = std::sync::mpsc::channel();
        let run = spawn_run(
            lcnc,
            &config_text,
            rig.options(dir.path(), tx, Default::default()),
            false,
        );
        wait_for_progress(&progress, 6);
        op.send("set enable EMCTOO");
        op.send("set estop on");
        // From the moment the E-stop shows: pressed, and the commanded position unchanged.
        let mut stopped_at: Option<String> = None;
        let mut readings = 0;
        let mut watch = |op: &mut Operator| {
            let estop = op.get("estop");
            let at = op.get("abs_cmd_pos");
            match &stopped_at {
                None if estop == "ON" => stopped_at = Some(at),
                None => {}
                Some(p) => {
                    assert_eq!(estop, "ON", "the E-stop was released");
                    assert_eq!(&at, p, "LinuxCNC moved after the E-stop");
                    readings += 1;
                }
            }
        };
        while !run.is_finished() {
            watch(&mut op);
            std::thread::sleep(Duration::from_millis(10));
        }
        let first = run.join().expect("run thread").expect("namespace");
        let settle = std::time::Instant::now();
        while settle.elapsed() < Duration::from_secs(3) {
            watch(&mut op);
            std::thread::sleep(Duration::from_millis(50));
        }
        assert!(stopped_at.is_some(), "the E-stop never showed");
        assert!(op.controller_state().starts_with("estop ON machine OFF"));
        println!(
            "stopped run: {:.1} s; E-stop and position unchanged in {readings} readings",
            started.elapsed().as_secs_f64()
        );
        let error = first.expect_err("the run went on through an E-stop it did not cause");
        assert!(
            error.contains("in E-stop")
                && error.contains("geocal run --resume")
                && error.contains("session recorded so far is kept"),
            "{error}"
        );
        let session_path = dir.path().join("session.mcap");
        let stopped = read_session(&session_path).expect("the stopped session reads");
        let events = run_events(&stopped);
        let alarms = common::faults(&events, "alarm");
        assert!(
            alarms.len() == 1 && alarms[0].1.contains("E-stop"),
            "the E-stop is one alarm: {alarms:?}"
        );
        let alarm_at = events
            .iter()
            .position(|e| matches!(e, RunEvent::Fault { code, .. } if code == "alarm"))
            .expect("alarm");
        assert!(
            !events[alarm_at..]
                .iter()
                .any(|e| matches!(e, RunEvent::PointBegin { .. })),
            "a point was begun after the E-stop"
        );
        let done_before = events
            .iter()
            .filter(|e| matches!(e, RunEvent::PointEnd { .. }))
            .count();
        assert!(done_before >= 6, "{done_before} points kept");
        assert_tracer_windows_whole(&stopped, 1);
        let (_, stopped_raw) = read_session_raw(&session_path).expect("raw");

        // The operator clears the E-stop at the machine; the run is resumed.
        op.send("set estop off");
        op.send("set machine on");
        op.wait_for("machine", "ON");
        if !op.get("joint_homed").starts_with("YES YES YES") {
            op.home_all(3);
        }
        rig.fresh_emulator(2);
        let (tx, _progress) = std::sync::mpsc::channel();
        let resumed = spawn_run(
            lcnc,
            &config_text,
            rig.options(dir.path(), tx, Default::default()),
            true,
        )
        .join()
        .expect("run thread")
        .expect("namespace");
        println!(
            "resumed: {resumed:?}, {:.1} s in all",
            started.elapsed().as_secs_f64()
        );
        resumed.expect("the resumed run completes");
        let (_, final_raw) = read_session_raw(&session_path).expect("raw final");
        assert!(final_raw.len() > stopped_raw.len());
        for (i, (a, b)) in stopped_raw.iter().zip(&final_raw).enumerate() {
            assert_eq!(
                (&a.channel.topic, a.log_time_ns, &a.data),
                (&b.channel.topic, b.log_time_ns, &b.data),
                "message {i} of the stopped session changed"
            );
        }
        let finished = read_session(&session_path).expect("final session");
        for (device, message) in common::faults(&run_events(&finished), "frames_lost") {
            println!("{device}: {message}");
        }
        assert!(finished.completeness.is_complete());
        assert_tracer_windows_whole(&finished, 2);
        let mut points: Vec<(String, usize)> = run_events(&finished)
            .into_iter()
            .filter_map(|e| match e {
                RunEvent::PointEnd { station, point, .. } => Some((station.to_string(), point)),
                _ => None,
            })
            .collect();
        points.sort();
        points.dedup();
        assert_eq!(
            points.len(),
            4 * 16,
            "every planned point measured: {points:?}"
        );

        // A run cancelled in the middle of a move (the daemon's cancel; Ctrl-C does the
        // same) stops it and leaves the controller as found: the operator's G91, no motion
        // mode (G80) and manual mode.
        op.send("set enable EMCTOO");
        op.send("set mode mdi");
        op.wait_for("mode", "MDI");
        op.send("set mdi G80 G91");
        op.send("set mode manual");
        op.wait_for("mode", "MANUAL");
        let found = op.controller_state();
        assert!(
            found.contains("codes G80 ") && found.contains(" G91 ") && found.contains("MANUAL"),
            "{found}"
        );
        rig.fresh_emulator(3);
        let cancelled_dir = tempfile::tempdir().expect("tempdir");
        let cancel = tokio_util::sync::CancellationToken::new();
        let (tx, progress) = std::sync::mpsc::channel();
        let run = spawn_run(
            lcnc,
            &config_text,
            rig.options(cancelled_dir.path(), tx, cancel.clone()),
            false,
        );
        wait_for_progress(&progress, 2);
        // The next move is being sent or made: cancel in the middle of it.
        std::thread::sleep(Duration::from_millis(100));
        cancel.cancel();
        let error = run
            .join()
            .expect("run thread")
            .expect("namespace")
            .expect_err("cancelled");
        assert!(error.contains("cancelled"), "{error}");
        let status = op.get("program_status");
        assert_eq!(status, "IDLE", "geocal's move stopped");
        assert_eq!(op.controller_state(), found, "left as found after a cancel");
        let kept = read_session(&cancelled_dir.path().join("session.mcap")).expect("kept");
        assert!(
            common::faults(&run_events(&kept), "finish").is_empty(),
            "finish recorded no fault"
        );
        println!(
            "whole-run test: {:.1} s in all",
            started.elapsed().as_secs_f64()
        );
    });
}
