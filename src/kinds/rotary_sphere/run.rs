//! A whole `rotary_sphere` run: config -> plan -> devices (simulated, emulated or real) ->
//! sequencer -> recorded session -> solve -> results, read back from the file as `solve` does.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use anyhow::Context;
use async_trait::async_trait;
use geocal_drivers::probe::{AsciiProbe, ProbeConfig, ProbeEmulator};
use geocal_drivers::{DeviceError, Probe, RotaryTable};

use crate::clock::{system_now_ns, Clock, SystemClock, VirtualClock};
use crate::config::DriverKind;
use crate::kinds::rotary_sphere::config::{ProbeDriverKind, RotarySphereConfig, KIND};
use crate::kinds::rotary_sphere::hil_source::SphereTableSource;
use crate::kinds::rotary_sphere::plan::SpherePlan;
use crate::kinds::rotary_sphere::sequence::{
    ProbeArm, SphereDevices, SphereRunSummary, SphereSequencer,
};
use crate::kinds::rotary_sphere::sim::{
    SharedSphereWorld, SimArm, SimSphereProbe, SimSphereTable, SphereWorld,
};
use crate::method::Results;
use crate::run::resume::Interruption;
use crate::run::RunOptions;
use crate::session::messages::{MachineInfo, RunEvent, SessionHeader, SESSION_FORMAT};
use crate::session::reader::Session;

pub struct SphereRunOutput {
    pub session_path: PathBuf,
    pub results_path: PathBuf,
    pub summary: SphereRunSummary,
    pub results: Results,
    /// Requests the probe emulator answered (emulated runs).
    pub emulator_requests: Option<u64>,
}

struct Built {
    devices: SphereDevices,
    clock: Arc<dyn Clock>,
    world: Option<SharedSphereWorld>,
    emulator: Option<ProbeEmulator>,
    /// The Modbus table emulator of an emulated (`[hil]`) run with a Modbus table.
    table_emulator: Option<crate::devices::rotary_table::HostedTable>,
}

/// An arm without a controller: the operator is told where to bring the probe.
struct LoggingArm;

#[async_trait]
impl ProbeArm for LoggingArm {
    async fn mount_sphere(
        &mut self,
        height_index: usize,
        nominal_m: [f64; 3],
    ) -> Result<(), DeviceError> {
        tracing::warn!(
            height_index,
            ?nominal_m,
            "mount the sphere at height {height_index}"
        );
        Ok(())
    }
    async fn approach(
        &mut self,
        start_m: [f64; 3],
        direction: [f64; 3],
    ) -> Result<(), DeviceError> {
        tracing::info!(
            ?start_m,
            ?direction,
            "bring the probe to the approach start"
        );
        Ok(())
    }
}

fn probe_config(config: &RotarySphereConfig) -> ProbeConfig {
    let mut c = config.devices.probe.ascii.clone().unwrap_or_default();
    c.id = config.devices.probe.id.clone();
    c
}

async fn build(
    config: &RotarySphereConfig,
    plan: &SpherePlan,
    epoch_ns: u64,
    holder: Option<&crate::devices::held::DeviceHolder>,
) -> anyhow::Result<Built> {
    let probe_cfg = &config.devices.probe;
    let table_cfg = &config.devices.rotary_table;
    let emulate = config.hil.as_ref().is_some_and(|h| h.emulate);
    let virtual_clock = Arc::new(VirtualClock::new(epoch_ns));
    let world: Option<SharedSphereWorld> = match &config.sim {
        Some(_) => Some(Arc::new(Mutex::new(
            SphereWorld::new(config, plan, virtual_clock.clone())
                .map_err(|e| anyhow::anyhow!("building the simulated world: {e}"))?,
        ))),
        None => None,
    };
    let all_sim = probe_cfg.driver == ProbeDriverKind::Sim && table_cfg.driver == DriverKind::Sim;
    let clock: Arc<dyn Clock> = if all_sim {
        virtual_clock
    } else {
        Arc::new(SystemClock)
    };
    let mut table_emulator = None;
    let table: Box<dyn RotaryTable> = match (table_cfg.driver, &world, &config.sim) {
        (DriverKind::Sim, Some(w), _) => Box::new(SimSphereTable {
            id: table_cfg.id.clone(),
            world: w.clone(),
        }),
        // Emulated: the Modbus table emulator backed by the sphere world, the real driver.
        (DriverKind::ModbusTcp | DriverKind::ModbusRtu, Some(w), Some(sim)) if emulate => {
            let faults = config
                .hil
                .as_ref()
                .map(|h| h.table_faults.clone())
                .unwrap_or_default();
            let source = SphereTableSource::new(w.clone(), sim.speed_rad_s, sim.settle_s);
            let hosted = crate::devices::rotary_table::host_emulator_with(
                table_cfg,
                &faults,
                Box::new(source),
            )
            .await?;
            let driver = crate::devices::rotary_table::connect_hosted(table_cfg, &hosted).await?;
            table_emulator = Some(hosted);
            driver
        }
        // A real table (no [sim]): the Modbus driver at its configured address.
        (DriverKind::ModbusTcp | DriverKind::ModbusRtu, None, _) => {
            crate::devices::rotary_table::connect_real(table_cfg, holder).await?
        }
        (kind, _, _) => anyhow::bail!(
            "devices.rotary_table.driver = \"{}\": a simulated rotary_sphere run needs the \"sim\" \
             table, or [hil] emulate = true to host the Modbus table emulator; Modbus tables \
             without [sim] are real",
            kind.as_str()
        ),
    };
    let mut emulator = None;
    let probe: Box<dyn Probe> = match (probe_cfg.driver, &world) {
        (ProbeDriverKind::Sim, Some(w)) => Box::new(SimSphereProbe {
            id: probe_cfg.id.clone(),
            world: w.clone(),
        }),
        (ProbeDriverKind::Ascii, Some(w)) if emulate => {
            let source_world = w.clone();
            let source = move |_t_s: f64| source_world.lock().ok()?.read_probe();
            let faults = config
                .hil
                .as_ref()
                .map(|h| h.probe_faults.clone())
                .unwrap_or_default();
            let (emu, driver) = crate::devices::hosting::host_ascii_probe(
                &probe_config(config),
                &faults,
                Box::new(source),
            )?;
            emulator = Some(emu);
            Box::new(driver)
        }
        (ProbeDriverKind::Ascii, _) => {
            let cfg = probe_config(config);
            let port = cfg.port.clone();
            crate::devices::held::lend_or_open(holder, &cfg.id.clone(), &cfg.clone(), || async {
                AsciiProbe::open(cfg).with_context(|| format!("opening the probe at {port}"))
            })
            .await?
        }
        (ProbeDriverKind::Sim, None) => {
            anyhow::bail!("devices.probe.driver = \"sim\" needs [sim] (validation checks this)")
        }
    };
    let arm: Box<dyn ProbeArm> = match &world {
        Some(w) => Box::new(SimArm { world: w.clone() }),
        None => Box::new(LoggingArm),
    };
    Ok(Built {
        devices: SphereDevices { table, probe, arm },
        clock,
        world,
        emulator,
        table_emulator,
    })
}

fn session_header(config: &RotarySphereConfig, epoch_ns: u64) -> SessionHeader {
    let started_at = crate::session::messages::started_at(epoch_ns);
    let seed = config
        .sim
        .as_ref()
        .map(|s| format!("-seed{}", s.seed))
        .unwrap_or_default();
    let table = &config.devices.rotary_table;
    let probe = &config.devices.probe;
    SessionHeader {
        format: SESSION_FORMAT.into(),
        session_id: format!("{KIND}-{}{seed}", epoch_ns / 1_000_000),
        started_at,
        kind: KIND.into(),
        machine: MachineInfo {
            name: config.machine.name.clone(),
            structure: "C".into(),
            axes: vec![table.id.clone()],
            travel_m: BTreeMap::new(),
            targets: Vec::new(),
        },
        devices: vec![
            crate::kinds::device(
                &table.id,
                "rotary_table",
                table.driver.as_str(),
                None,
                BTreeMap::new(),
            ),
            crate::kinds::device(
                &probe.id,
                "probe",
                probe.driver.as_str(),
                Some(probe.noise_m),
                BTreeMap::new(),
            ),
        ],
        plan: serde_json::to_value(&config.plan).unwrap_or_default(),
    }
}

pub fn run(config: &RotarySphereConfig, options: &RunOptions) -> anyhow::Result<SphereRunOutput> {
    std::fs::create_dir_all(&options.out_dir)
        .with_context(|| format!("creating output directory {}", options.out_dir.display()))?;
    crate::run::resume::store_config(config, &options.out_dir)?;
    execute(config, options, None)
}

/// `geocal run [CONFIG] --resume DIR` of a rotary_sphere run: the spheres the interrupted run
/// finished are kept, the run continues at the first unfinished one.
pub fn resume(
    dir: &Path,
    config: Option<&Path>,
    options: &RunOptions,
) -> anyhow::Result<SphereRunOutput> {
    let (config, interruption) = crate::run::resume::read_interrupted_run(
        dir,
        config,
        KIND,
        |p| Ok(RotarySphereConfig::load(p)?),
        |c: &RotarySphereConfig| &c.plan,
    )?;
    let plan = SpherePlan::from_config(&config.plan);
    let first = first_unfinished_sphere(&plan, &interruption.session);
    tracing::info!(
        kept = interruption.messages_kept(),
        "resuming {} at sphere {first:?}",
        dir.display()
    );
    execute(&config, options, Some((interruption, first)))
}

/// The first sphere (height, angle index) in plan order without a `sphere_end`; (heights, 0)
/// when every sphere is finished.
fn first_unfinished_sphere(plan: &SpherePlan, session: &Session) -> (usize, usize) {
    let finished: BTreeSet<(usize, usize)> = session
        .events
        .iter()
        .filter_map(|e| match e.msg {
            RunEvent::SphereEnd {
                height_index,
                angle_index,
            } => Some((height_index, angle_index)),
            _ => None,
        })
        .collect();
    (0..plan.heights.len())
        .flat_map(|h| (0..plan.angles_rad.len()).map(move |a| (h, a)))
        .find(|sphere| !finished.contains(sphere))
        .unwrap_or((plan.heights.len(), 0))
}

/// A run from the start, or the continuation of an interrupted one at a sphere.
fn execute(
    config: &RotarySphereConfig,
    options: &RunOptions,
    mut continuation: Option<(Interruption, (usize, usize))>,
) -> anyhow::Result<SphereRunOutput> {
    let mut plan = SpherePlan::from_config(&config.plan);
    // The simulated table spends virtual time on each state query: no wall-time pause.
    if config.devices.rotary_table.driver == DriverKind::Sim {
        plan.poll_interval_s = 0.0;
    }
    let simulated = config.devices.probe.driver == ProbeDriverKind::Sim
        && config.devices.rotary_table.driver == DriverKind::Sim;
    let epoch_ns = continuation
        .as_ref()
        .map_or_else(system_now_ns, |(c, _)| c.epoch_ns(simulated));
    let runtime = crate::run::run_runtime(&options.control, config.sim.is_none())?;
    let built = runtime.block_on(build(
        config,
        &plan,
        epoch_ns,
        options.control.devices.as_deref(),
    ))?;
    if let Some((interruption, _)) = continuation.as_mut() {
        if !simulated {
            interruption.wait_for_clock(built.clock.as_ref())?;
        }
        interruption.set_aside()?;
    }
    let (session_path, recorder) = crate::run::create_session(options)?;
    let handle = recorder.handle();
    let mut first_sphere = (0, 0);
    match continuation.as_mut() {
        Some((interruption, first)) => {
            if let (true, Some(world), Some(sim)) = (simulated, &built.world, &config.sim) {
                let (t_s, noise_seed) = interruption.simulated_restart(sim.seed);
                world
                    .lock()
                    .map_err(|_| anyhow::anyhow!("simulated world poisoned"))?
                    .resume_at(t_s, noise_seed);
            }
            let event = RunEvent::Resume {
                resume_index: interruption.resume_index,
                messages_kept: interruption.messages_kept(),
                station: None,
                target: None,
                pass: None,
                point: None,
                height_index: (first.0 < plan.heights.len()).then_some(first.0),
                angle_index: (first.0 < plan.heights.len()).then_some(first.1),
                posture: None,
                pose: None,
            };
            interruption.record_copy(&handle, event, built.clock.as_ref());
            first_sphere = *first;
        }
        None => handle.session(&session_header(config, epoch_ns), built.clock.now_ns()),
    }
    let bar = crate::run::progress_bar(options.progress, "probed points");
    let mut progress = |done: u64, total: u64| {
        bar.set_length(total);
        bar.set_position(done);
        options.control.report_progress(done, total);
    };
    let sequencer = SphereSequencer::new(&plan, built.devices, handle, built.clock.clone())
        .resume_at(first_sphere);
    let summary = runtime.block_on(
        options
            .control
            .until_cancelled(sequencer.run(&mut progress)),
    );
    let emulator_requests = built.emulator.as_ref().map(|e| {
        e.stats()
            .requests
            .load(std::sync::atomic::Ordering::Relaxed)
    });
    drop(built.emulator);
    drop(built.table_emulator);
    bar.finish_and_clear();
    // Finish the file even after a failed run: every recorded reading stays readable.
    let stats = recorder.finish().context("finishing the session file")?;
    let summary = summary.context("run failed (the session recorded so far is kept)")?;
    if let Some((interruption, _)) = &continuation {
        interruption.finished(&session_path)?;
    }
    tracing::info!(
        readings = summary.readings,
        bytes = stats.bytes,
        "run recorded to {}",
        session_path.display()
    );
    if let (Some(path), Some(world)) = (&options.truth, &built.world) {
        let world = world
            .lock()
            .map_err(|_| anyhow::anyhow!("simulated world poisoned"))?;
        crate::run::write_truth(path, &world.export_truth(&plan))?;
    }
    let (results, results_path) = crate::kinds::registry::solve_and_write(&session_path, options)?;
    Ok(SphereRunOutput {
        session_path,
        results_path,
        summary,
        results,
        emulator_requests,
    })
}
