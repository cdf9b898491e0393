//! A whole `hexapod` run: the devices (simulated, Modbus emulated under `[hil]`, or real),
//! the kind's sequencer, the recording, the truth export and the solve of the recorded file.

use std::collections::BTreeMap;

use crate::clock::system_now_ns;
use crate::kinds::hexapod::config::{HexapodConfig, KIND};
use crate::kinds::hexapod::plan::{HexapodPlan, POSE_AXES};
use crate::kinds::hexapod::sequence::HexapodSequencer;
use crate::run::{RunOptions, RunOutput};
use crate::session::messages::{MachineInfo, SessionHeader, SESSION_FORMAT};

/// The header: the hexapod device carries the design hinges (`design`), the solver's start.
pub fn session_header(config: &HexapodConfig, epoch_ns: u64) -> SessionHeader {
    let h = &config.devices.hexapod;
    let seed = config
        .sim
        .as_ref()
        .map(|s| format!("-seed{}", s.seed))
        .unwrap_or_default();
    let mut devices = vec![crate::kinds::device(
        &h.id,
        "hexapod",
        h.driver.as_str(),
        Some(h.encoder_noise_m),
        BTreeMap::from([
            (
                "design".into(),
                serde_json::to_value(&config.machine).unwrap_or_default(),
            ),
            ("speed_m_s".into(), h.speed_m_s.into()),
            ("angular_speed_rad_s".into(), h.angular_speed_rad_s.into()),
            ("reading_period_s".into(), h.reading_period_s.into()),
        ]),
    )];
    if let Some(modbus) = &h.modbus {
        // The register map and timing the run used (the transport, unless emulated).
        let mut m = serde_json::to_value(modbus).unwrap_or_default();
        if let Some(o) = m.as_object_mut() {
            o.remove("id");
            o.insert("emulated".into(), config.emulated().into());
        }
        devices[0].extra.insert("modbus".into(), m);
    }
    if let Some(s) = &config.devices.pose_sensor {
        devices.push(crate::kinds::device(
            &s.id,
            "pose_sensor",
            s.driver.as_str(),
            Some(s.noise_m),
            BTreeMap::from([("noise_rad".into(), s.noise_rad.into())]),
        ));
    }
    SessionHeader {
        format: SESSION_FORMAT.into(),
        session_id: format!("{KIND}-{}{seed}", epoch_ns / 1_000_000),
        started_at: crate::session::messages::started_at(epoch_ns),
        kind: KIND.into(),
        machine: MachineInfo {
            name: config.machine.name.clone(),
            structure: "hexapod".into(),
            axes: POSE_AXES.iter().map(|a| a.to_string()).collect(),
            travel_m: BTreeMap::new(),
            targets: Vec::new(),
        },
        devices,
        plan: serde_json::to_value(&config.plan).unwrap_or_default(),
    }
}

pub fn run(config: &HexapodConfig, options: &RunOptions) -> anyhow::Result<RunOutput> {
    let plan = HexapodPlan::from_config(config);
    let epoch_ns = system_now_ns();
    let runtime = crate::run::run_runtime()?;
    let built = runtime.block_on(super::devices::build(config, epoch_ns))?;
    let (session_path, recorder) = crate::run::create_session(&options.out_dir)?;
    let handle = recorder.handle();
    handle.session(&session_header(config, epoch_ns), built.clock.now_ns());
    let poll_s = config
        .devices
        .hexapod
        .modbus
        .as_ref()
        .map_or(0.0, |m| m.poll_interval_s);
    let sequencer = HexapodSequencer::new(&plan, built.devices, handle, built.clock.clone())
        .with_poll_interval(poll_s);
    let summary = runtime.block_on(sequencer.run(&mut |_: u64, _: u64| {}));
    if let Some(hosted) = &built.hosted {
        tracing::info!(stats = ?hosted.emulator.stats(), "Modbus hexapod emulator");
    }
    drop(built.hosted);
    match (&options.truth, &built.world) {
        (Some(path), Some(world)) => {
            let truth = world
                .lock()
                .map_err(|_| anyhow::anyhow!("simulated world poisoned"))?
                .truth();
            crate::run::write_truth(path, &truth)?;
        }
        (Some(path), None) => tracing::warn!(
            "no truth to write to {}: a real hexapod run has no simulated world",
            path.display()
        ),
        _ => {}
    }
    crate::kinds::finish_and_solve(recorder, summary, session_path, options, None)
}
