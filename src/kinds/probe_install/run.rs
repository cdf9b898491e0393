//! A whole `probe_install` run: devices (simulated in virtual time, GRBL + ASCII drivers on real
//! ports or on `[hil]` pty emulators), sequencer, recording, truth export, solve of the file;
//! and the continuation of an interrupted run (`geocal run --resume`).

use std::collections::BTreeMap;
use std::path::Path;
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
use crate::run::resume::Interruption;
use crate::run::{RunOptions, RunOutput};
use crate::session::messages::{MachineInfo, RunEvent, SessionHeader, SESSION_FORMAT};
use crate::session::reader::Session;
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
            // ISO 230-1 chain as the shared session format defines it: every axis on the tool
            // branch, from the frame outward (B carries A).
            structure: "FXYZBA".into(),
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
    std::fs::create_dir_all(&options.out_dir)
        .with_context(|| format!("creating output directory {}", options.out_dir.display()))?;
    crate::run::resume::store_config(config, &options.out_dir)?;
    execute(config, options, None)
}

/// Where an interrupted run goes on, read from its recording.
struct Continuation {
    interruption: Interruption,
    /// The first posture without `posture_end` (the number of postures: none left).
    posture: usize,
    /// The `seq` of the next probe reading.
    next_seq: u64,
    /// The last machine position the interrupted run commanded (x, y, z, a, b).
    machine_at: Option<[f64; 5]>,
}

/// `geocal run [CONFIG] --resume DIR` of a probe_install run: the postures the interrupted
/// run finished are kept, the run continues at the first unfinished one (measured again in
/// full; the solver sets the interrupted attempt's readings aside).
pub fn resume(
    dir: &Path,
    config: Option<&Path>,
    options: &RunOptions,
) -> anyhow::Result<RunOutput> {
    let (config, interruption) = crate::run::resume::read_interrupted_run(
        dir,
        config,
        KIND,
        |p| Ok(ProbeInstallConfig::load(p)?),
        |c: &ProbeInstallConfig| &c.plan,
    )?;
    let plan = ProbeInstallPlan::from_config(&config);
    let session = &interruption.session;
    let posture = first_unfinished_posture(&plan, session);
    let next_seq = session
        .probes
        .values()
        .flatten()
        .map(|r| r.msg.seq + 1)
        .max()
        .unwrap_or(1);
    let machine_at = last_commanded(session);
    tracing::info!(
        kept = interruption.messages_kept(),
        "resuming {} at posture {posture}",
        dir.display()
    );
    let continuation = Continuation {
        interruption,
        posture,
        next_seq,
        machine_at,
    };
    execute(&config, options, Some(continuation))
}

/// The first posture in plan order without a `posture_end`; the number of postures when
/// every one is finished.
fn first_unfinished_posture(plan: &ProbeInstallPlan, session: &Session) -> usize {
    crate::run::resume::first_unfinished(plan.postures_rad.len(), session, |e| match e {
        RunEvent::PostureEnd { posture } => Some(*posture),
        _ => None,
    })
}

/// The machine position of the last `probe_begin` (where the machine stood when the run was
/// interrupted, give or take the move that was under way).
fn last_commanded(session: &Session) -> Option<[f64; 5]> {
    session.events.iter().rev().find_map(|e| match &e.msg {
        RunEvent::ProbeBegin { axes, .. } => {
            let v: Option<Vec<f64>> = CMM_AXES.iter().map(|a| axes.get(a).copied()).collect();
            v.and_then(|v| <[f64; 5]>::try_from(v).ok())
        }
        _ => None,
    })
}

/// A run's devices, its log clock and the simulated world behind them (simulated and
/// emulated runs).
struct Built {
    devices: ProbeInstallDevices,
    clock: Arc<dyn Clock>,
    world: Option<SharedProbeWorld>,
    emulators: Option<Emulated>,
}

/// The devices: simulated in virtual time, or the GRBL and ASCII drivers (real, or under
/// `[hil]` against the emulators). Must run inside the runtime that runs the sequencer.
async fn build(
    config: &ProbeInstallConfig,
    epoch_ns: u64,
    holder: Option<&crate::devices::held::DeviceHolder>,
) -> anyhow::Result<Built> {
    if config.all_sim() {
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
        return Ok(Built {
            devices,
            clock,
            world: Some(world),
            emulators: None,
        });
    }
    // An emulated run's world follows wall time (its own clock is advanced to `HilTime` at
    // every emulator call); the session is stamped by the same `HilTime`.
    let time = Arc::new(HilTime::new(epoch_ns));
    let world: Option<SharedProbeWorld> = config.emulated().then(|| {
        Arc::new(Mutex::new(ProbeInstallWorld::new(
            config,
            Arc::new(VirtualClock::new(epoch_ns)),
        )))
    });
    let clock: Arc<dyn Clock> = if config.emulated() {
        time.clone()
    } else {
        Arc::new(SystemClock)
    };
    let (devices, emulators) = connect(config, world.as_ref().map(|w| (w, &time)), holder).await?;
    Ok(Built {
        devices,
        clock,
        world,
        emulators,
    })
}

/// A run from the start, or the continuation of an interrupted one at a posture.
fn execute(
    config: &ProbeInstallConfig,
    options: &RunOptions,
    mut continuation: Option<Continuation>,
) -> anyhow::Result<RunOutput> {
    let plan = ProbeInstallPlan::from_config(config);
    let simulated = config.all_sim();
    let epoch_ns = continuation
        .as_ref()
        .map_or_else(system_now_ns, |c| c.interruption.epoch_ns(simulated));
    let real_devices = !simulated && !config.emulated();
    let runtime = crate::run::run_runtime(&options.control, real_devices)?;
    let built = runtime.block_on(build(config, epoch_ns, options.control.devices.as_deref()))?;
    if let Some(c) = continuation.as_mut() {
        if !simulated {
            c.interruption.wait_for_clock(built.clock.as_ref())?;
        }
        c.interruption.set_aside()?;
    }
    let (session_path, recorder) = crate::run::create_session(options)?;
    let handle = recorder.handle();
    let mut interruption = None;
    let mut first = (0, 1);
    match continuation {
        Some(mut c) => {
            if let (Some(world), Some(sim)) = (&built.world, &config.sim) {
                let (t_s, noise_seed) = c.interruption.simulated_restart(sim.seed);
                world
                    .lock()
                    .map_err(|_| anyhow::anyhow!("simulated world poisoned"))?
                    .resume_at(simulated.then_some(t_s), noise_seed, c.machine_at);
            }
            let left = c.posture < plan.postures_rad.len();
            let event = RunEvent::Resume {
                resume_index: c.interruption.resume_index,
                messages_kept: c.interruption.messages_kept(),
                station: None,
                target: None,
                pass: None,
                point: None,
                height_index: None,
                angle_index: None,
                posture: left.then_some(c.posture),
                pose: None,
            };
            c.interruption
                .record_copy(&handle, event, built.clock.as_ref());
            first = (c.posture, c.next_seq);
            interruption = Some(c.interruption);
        }
        None => handle.session(&session_header(config, epoch_ns), built.clock.now_ns()),
    }
    let sequencer = ProbeInstallSequencer::new(&plan, built.devices, handle, built.clock.clone())
        .resume_at(first.0, first.1);
    let summary = runtime.block_on(options.control.until_cancelled(
        sequencer.run(&mut |done: u64, total: u64| options.control.report_progress(done, total)),
    ));
    drop(built.emulators);
    if let (Some(path), Some(world)) = (&options.truth, &built.world) {
        let truth = world
            .lock()
            .map_err(|_| anyhow::anyhow!("simulated world poisoned"))?
            .truth();
        crate::run::write_truth(path, &truth)?;
    }
    crate::kinds::finish_and_solve(
        recorder,
        summary,
        session_path,
        options,
        interruption.as_ref(),
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
    holder: Option<&crate::devices::held::DeviceHolder>,
) -> anyhow::Result<(ProbeInstallDevices, Option<Emulated>)> {
    let mut grbl = config.grbl_config();
    let probe_cfg = config.probe_config();
    let Some((world, time)) = hil else {
        use crate::devices::held::lend_or_open;
        let machine = lend_or_open(holder, &grbl.id.clone(), &grbl.clone(), || async {
            let at = format!("opening the GRBL controller at {}", grbl.port);
            GrblMachine::open(grbl).context(at)
        })
        .await?;
        let probe = lend_or_open(
            holder,
            &probe_cfg.id.clone(),
            &probe_cfg.clone(),
            || async {
                let at = format!("opening the probe at {}", probe_cfg.port);
                AsciiProbe::open(probe_cfg).context(at)
            },
        )
        .await?;
        let devices = ProbeInstallDevices { machine, probe };
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

#[cfg(test)]
mod tests {
    use super::*;

    /// `--resume DIR` runs on the configuration stored at run start: it must read back as
    /// the one the run started with.
    #[test]
    fn the_stored_configuration_reads_back_equal() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/config/probe-install.toml");
        let config = ProbeInstallConfig::load(Path::new(path)).expect("example config");
        let dir = tempfile::tempdir().expect("temp dir");
        crate::run::resume::store_config(&config, dir.path()).expect("store");
        let stored = dir.path().join(crate::run::resume::CONFIG_FILE);
        assert_eq!(
            ProbeInstallConfig::load(&stored).expect("stored config"),
            config
        );
    }
}
