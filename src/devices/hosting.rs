//! Hosting the configured device emulators backed by the simulated world: the HPI-3D and
//! GRBL emulators on ptys, the Modbus table on 127.0.0.1 or a pty. Used by `[hil]` runs
//! (src/devices/mod.rs) and by `geocal simulate` (src/run/simulate.rs); the ASCII probe emulator with
//! its driver for the kinds that read a probe (`host_ascii_probe`).

use std::sync::Arc;

use anyhow::Context;
use geocal_drivers::grbl::{GrblEmulator, GrblEmulatorConfig};
use geocal_drivers::hpi3d::{EmulatorConfig, Hpi3dEmulator};
use geocal_drivers::serial::SerialStream;

use crate::config::{Config, DriverKind, HilConfig, SimConfig};
use crate::devices::rotary_table::HostedTable;
use crate::sim::devices::SharedWorld;
use crate::sim::hil::{HilTime, WorldMachineSink, WorldTracerSource};

/// The hosted emulators; dropping this stops them and removes the link directory.
pub struct Hosted {
    pub tracer: Hpi3dEmulator,
    /// The host end of the tracer's pty (kept open; a driver here may use it directly).
    pub tracer_port: Option<SerialStream>,
    pub tracer_path: String,
    /// The GRBL emulator (machine driver `grbl`), reached through a stable link path that
    /// survives an injected disconnect.
    pub machine: Option<GrblEmulator>,
    pub machine_path: Option<String>,
    /// The Modbus table emulator (table driver `modbus_tcp` / `modbus_rtu`).
    pub table: Option<HostedTable>,
    /// A real LinuxCNC (machine driver `linuxcnc`, real-controller HIL) whose joints the
    /// world follows.
    pub linuxcnc: Option<crate::sim::linuxcnc::host::HostedLinuxCnc>,
    /// Holds the links; removed on drop (declared last: dropped after the emulators).
    pub link_dir: LinkDir,
}

/// A private directory for the emulators' link paths, removed on drop (a unique name per
/// run, so that runs in one process never share it).
pub struct LinkDir(pub tempfile::TempDir);

impl LinkDir {
    pub(crate) fn create() -> anyhow::Result<Self> {
        tempfile::Builder::new()
            .prefix("geocal-emulators-")
            .tempdir()
            .map(Self)
            .context("creating the emulators' link directory")
    }

    pub fn path(&self) -> &std::path::Path {
        self.0.path()
    }
}

/// Host every emulator the configuration asks for. Must run inside the tokio runtime that
/// will serve them.
pub async fn host(
    config: &Config,
    sim: &SimConfig,
    hil: &HilConfig,
    world: &SharedWorld,
    time: &Arc<HilTime>,
) -> anyhow::Result<Hosted> {
    let link_dir = LinkDir::create()?;
    // The tracer: the HPI-3D emulator on a pty.
    let tracer_cfg = &config.devices.tracer;
    let meteo_period_s = config
        .devices
        .environment
        .as_ref()
        .map_or(1.0, |e| 1.0 / e.sample_rate_hz);
    let source = WorldTracerSource::new(
        world.clone(),
        time.clone(),
        tracer_cfg.noise_model(),
        sim.seed,
    );
    let (tracer, tracer_port) = Hpi3dEmulator::spawn_pty(
        EmulatorConfig {
            rate_hz: tracer_cfg.sample_rate_hz,
            meteo_period_s,
            faults: hil.tracer_faults.clone(),
        },
        Box::new(source),
    )
    .context("starting the HPI-3D emulator on a pty")?;
    let tracer_path = tracer
        .slave_path()
        .context("the HPI-3D emulator's pty has no path")?
        .display()
        .to_string();

    // The machine: the GRBL emulator on a pty behind a link path.
    let machine = if config.devices.machine.driver == DriverKind::Grbl {
        let travel = |k: usize| {
            config
                .machine
                .travel_m
                .get(crate::plan::AXES[k])
                .copied()
                .unwrap_or([-1.0, 1.0])
        };
        Some(
            GrblEmulator::spawn_pty_linked(
                GrblEmulatorConfig {
                    travel_min_m: std::array::from_fn(|k| travel(k)[0]),
                    travel_max_m: std::array::from_fn(|k| travel(k)[1]),
                    faults: hil.machine_faults.clone(),
                    ..GrblEmulatorConfig::default()
                },
                Box::new(WorldMachineSink::new(world.clone(), time.clone())),
                link_dir.path().join("grbl"),
            )
            .context("starting the GRBL emulator on a pty")?,
        )
    } else {
        None
    };
    let machine_path = machine
        .as_ref()
        .and_then(|m| m.slave_path().map(str::to_string));

    // The machine: a real LinuxCNC started headless; the world's carriages follow its joints.
    let linuxcnc = if config.linuxcnc_in_the_loop() {
        let setup = crate::sim::linuxcnc::MachineSetup::from_config(config);
        let timeout = std::time::Duration::from_secs_f64(
            hil.linuxcnc.as_ref().map_or(180.0, |l| l.start_timeout_s),
        );
        let hosted = tokio::task::spawn_blocking(move || {
            crate::sim::linuxcnc::host::HostedLinuxCnc::start(&setup, timeout)
        })
        .await
        .context("starting LinuxCNC")?
        .context("starting LinuxCNC for the real-controller HIL run")?;
        world
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .follow_joints(hosted.joint_source());
        Some(hosted)
    } else {
        None
    };

    // The rotary table: the Modbus table emulator.
    let table = match config.devices.rotary_table.as_ref() {
        Some(table) if table.driver != DriverKind::Sim => Some(
            crate::devices::rotary_table::host_emulator(
                table,
                &hil.table_faults,
                world.clone(),
                time.clone(),
            )
            .await?,
        ),
        _ => None,
    };
    Ok(Hosted {
        tracer,
        tracer_port: Some(tracer_port),
        tracer_path,
        machine,
        machine_path,
        table,
        linuxcnc,
        link_dir,
    })
}

/// The ASCII probe emulator on a pty, answering `cfg`'s command in its default reply format
/// with values from `source` and injecting `faults`, and the real driver (`cfg`, port taken
/// from the pty) connected to it. Must run inside the tokio runtime that will serve them.
pub fn host_ascii_probe(
    cfg: &geocal_drivers::probe::ProbeConfig,
    faults: &geocal_drivers::probe::ProbeFaults,
    source: Box<dyn geocal_drivers::probe::ProbeSource>,
) -> anyhow::Result<(
    geocal_drivers::probe::ProbeEmulator,
    geocal_drivers::probe::AsciiProbe<SerialStream>,
)> {
    use geocal_drivers::probe::{AsciiProbe, ProbeEmulator, ProbeEmulatorConfig};
    let mut cfg = cfg.clone();
    let mut emu = ProbeEmulator::spawn_pty(
        ProbeEmulatorConfig {
            command: cfg.command.trim().to_string(),
            scale_to_m: cfg.scale_to_m,
            faults: faults.clone(),
            ..ProbeEmulatorConfig::default()
        },
        source,
    )
    .context("starting the probe emulator on a pty")?;
    cfg.port = emu.slave_path().unwrap_or_default().to_string();
    tracing::info!("probe emulator on {}", cfg.port);
    let port = emu
        .take_slave()
        .context("the probe emulator's pty has no slave end")?;
    let driver = AsciiProbe::from_stream(port, cfg)?;
    Ok((emu, driver))
}
