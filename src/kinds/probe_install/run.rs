//! A whole `probe_install` run: devices (simulated in virtual time, GRBL + ASCII drivers on real
//! ports or on `[hil]` pty emulators), sequencer, recording, truth export, solve of the file.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use anyhow::Context;
use geocal_drivers::grbl::{GrblEmulator, GrblEmulatorConfig, GrblMachine};
use geocal_drivers::probe::{AsciiProbe, ProbeEmulator};

use crate::clock::{system_now_ns, Clock, SystemClock, VirtualClock};
use crate::kinds::probe_install::config::{ProbeInstallConfig, KIND};
use crate::kinds::probe_install::hil_source::{WorldCmmSink, WorldLaserSource};
use crate::kinds::probe_install::plan::{ProbeInstallPlan, CMM_AXES};
use crate::kinds::probe_install::sequence::{ProbeInstallDevices, ProbeInstallSequencer};
use crate::kinds::probe_install::sim::{
    ProbeInstallWorld, SharedProbeWorld, SimCmm, SimLaserProbe,
};
use crate::run::{RunOptions, RunOutput};
use crate::session::messages::{MachineInfo, SessionHeader, SESSION_FORMAT};
use crate::sim::hil::HilTime;

pub fn session_header(config: &ProbeInstallConfig, epoch_ns: u64) -> SessionHeader {
    let m = &config.devices.machine;
    let p = &config.devices.probe;
    let seed = config
        .sim
        .as_ref()
        .map(|s| format!("-seed{}", s.seed))
        .unwrap_or_default();
    SessionHeader {
        format: SESSION_FORMAT.into(),
        session_id: format!("{KIND}-{}{seed}", epoch_ns / 1_000_000),
        started_at: crate::session::messages::started_at(epoch_ns),
        kind: KIND.into(),
        machine: MachineInfo {
            name: config.machine.name.clone(),
            structure: "XYZAB".into(),
            axes: CMM_AXES.iter().map(|a| a.to_string()).collect(),
            travel_m: config.machine.travel_m.clone(),
            targets: Vec::new(),
        },
        devices: vec![
            crate::kinds::device(
                &m.id,
                "machine",
                m.driver.as_str(),
                None,
                BTreeMap::from([
                    ("feed_m_s".into(), m.feed_m_s.into()),
                    ("rotary_speed_rad_s".into(), m.rotary_speed_rad_s.into()),
                ]),
            ),
            crate::kinds::device(
                &p.id,
                "probe",
                p.driver.as_str(),
                Some(p.noise_m),
                BTreeMap::from([
                    ("range_m".into(), serde_json::json!(p.range_m)),
                    ("reading_period_s".into(), p.reading_period_s.into()),
                ]),
            ),
        ],
        plan: serde_json::to_value(&config.plan).unwrap_or_default(),
    }
}

pub fn run(config: &ProbeInstallConfig, options: &RunOptions) -> anyhow::Result<RunOutput> {
    if !config.all_sim() {
        return run_on_drivers(config, options);
    }
    let plan = ProbeInstallPlan::from_config(config);
    let epoch_ns = system_now_ns();
    let clock = Arc::new(VirtualClock::new(epoch_ns));
    let world = Arc::new(Mutex::new(ProbeInstallWorld::new(config, clock.clone())));
    let devices = ProbeInstallDevices {
        machine: Box::new(SimCmm {
            id: config.devices.machine.id.clone(),
            world: world.clone(),
        }),
        probe: Box::new(SimLaserProbe {
            id: config.devices.probe.id.clone(),
            world: world.clone(),
        }),
    };
    crate::kinds::record_and_solve(
        &session_header(config, epoch_ns),
        clock.as_ref(),
        options,
        |handle| async {
            let sequencer = ProbeInstallSequencer::new(&plan, devices, handle, clock.clone());
            sequencer.run(&mut |_: u64, _: u64| {}).await
        },
        || {
            Ok(world
                .lock()
                .map_err(|_| anyhow::anyhow!("simulated world poisoned"))?
                .truth())
        },
    )
}

/// The emulators of an emulated run (dropping them stops them) and their link directory.
struct Emulated {
    _machine: GrblEmulator,
    _probe: ProbeEmulator,
    _links: crate::devices::hosting::LinkDir,
}

/// The GRBL and ASCII drivers: at their configured ports, or under `[hil]` against the
/// emulators hosted here. Must run inside the runtime that runs the sequencer.
async fn connect(
    config: &ProbeInstallConfig,
    hil: Option<(&SharedProbeWorld, &Arc<HilTime>)>,
) -> anyhow::Result<(ProbeInstallDevices, Option<Emulated>)> {
    let mut grbl = config.grbl_config();
    let probe_cfg = config.probe_config();
    let Some((world, time)) = hil else {
        let machine = GrblMachine::open(grbl.clone())
            .with_context(|| format!("opening the GRBL controller at {}", grbl.port))?;
        let probe = AsciiProbe::open(probe_cfg.clone())
            .with_context(|| format!("opening the probe at {}", probe_cfg.port))?;
        let devices = ProbeInstallDevices {
            machine: Box::new(machine),
            probe: Box::new(probe),
        };
        return Ok((devices, None));
    };
    let (machine_faults, probe_faults) = config
        .hil
        .as_ref()
        .map(|h| (h.machine_faults.clone(), h.probe_faults.clone()))
        .unwrap_or_default();
    // The controller behind a stable link path, so that a pulled cable can be re-plugged.
    let links = crate::devices::hosting::LinkDir::create()?;
    let travel = |axis: &str| {
        config
            .machine
            .travel_m
            .get(axis)
            .copied()
            .unwrap_or([-1.0, 1.0])
    };
    let machine_emu = GrblEmulator::spawn_pty_linked(
        GrblEmulatorConfig {
            travel_min_m: ["x", "y", "z"].map(|a| travel(a)[0]),
            travel_max_m: ["x", "y", "z"].map(|a| travel(a)[1]),
            faults: machine_faults,
            ..GrblEmulatorConfig::default()
        },
        Box::new(WorldCmmSink::new(world.clone(), time.clone())),
        links.path().join("grbl"),
    )
    .context("starting the GRBL emulator on a pty")?;
    grbl.port = machine_emu
        .slave_path()
        .context("the GRBL emulator has no link path")?
        .to_string();
    tracing::info!("GRBL emulator on {}", grbl.port);
    let machine = GrblMachine::open(grbl)?;
    let (probe_emu, probe) = crate::devices::hosting::host_ascii_probe(
        &probe_cfg,
        &probe_faults,
        Box::new(WorldLaserSource::new(world.clone(), time.clone())),
    )?;
    let devices = ProbeInstallDevices {
        machine: Box::new(machine),
        probe: Box::new(probe),
    };
    let emulated = Emulated {
        _machine: machine_emu,
        _probe: probe_emu,
        _links: links,
    };
    Ok((devices, Some(emulated)))
}

/// A run on the GRBL and ASCII drivers, real or emulated (in real time).
fn run_on_drivers(config: &ProbeInstallConfig, options: &RunOptions) -> anyhow::Result<RunOutput> {
    let plan = ProbeInstallPlan::from_config(config);
    let epoch_ns = system_now_ns();
    let emulate = config.emulated();
    // An emulated run's world follows wall time (its own clock is advanced to `HilTime` at
    // every emulator call); the session is stamped by the same `HilTime`.
    let time = Arc::new(HilTime::new(epoch_ns));
    let world: Option<SharedProbeWorld> = emulate.then(|| {
        Arc::new(Mutex::new(ProbeInstallWorld::new(
            config,
            Arc::new(VirtualClock::new(epoch_ns)),
        )))
    });
    let clock: Arc<dyn Clock> = if emulate {
        time.clone()
    } else {
        Arc::new(SystemClock)
    };
    let runtime = crate::run::run_runtime()?;
    let (devices, emulators) =
        runtime.block_on(connect(config, world.as_ref().map(|w| (w, &time))))?;
    let (session_path, recorder) = crate::run::create_session(&options.out_dir)?;
    let handle = recorder.handle();
    handle.session(&session_header(config, epoch_ns), clock.now_ns());
    let sequencer = ProbeInstallSequencer::new(&plan, devices, handle, clock.clone());
    let summary = runtime.block_on(sequencer.run(&mut |_: u64, _: u64| {}));
    drop(emulators);
    if let (Some(path), Some(world)) = (&options.truth, &world) {
        let truth = world
            .lock()
            .map_err(|_| anyhow::anyhow!("simulated world poisoned"))?
            .truth();
        crate::run::write_truth(path, &truth)?;
    }
    crate::kinds::finish_and_solve(recorder, summary, session_path, options)
}
