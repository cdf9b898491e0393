//! A whole simulated `hexapod` run: the hexapod and pose sensor of the simulated world, the
//! kind's sequencer, the recording, the truth export and the solve of the recorded file.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use crate::clock::{system_now_ns, VirtualClock};
use crate::config::hexapod::{HexapodConfig, KIND};
use crate::plan::hexapod::{HexapodPlan, POSE_AXES};
use crate::run::{RunOptions, RunOutput};
use crate::sequencer::hexapod::{HexapodDevices, HexapodSequencer};
use crate::session::messages::{MachineInfo, SessionHeader, SESSION_FORMAT};
use crate::sim::hexapod::{HexapodWorld, SimHexapod, SimPoseSensor};

/// The header: the hexapod device carries the design hinges (`design`), the solver's start.
pub fn session_header(config: &HexapodConfig, epoch_ns: u64) -> SessionHeader {
    let h = &config.devices.hexapod;
    let seed = config
        .sim
        .as_ref()
        .map(|s| format!("-seed{}", s.seed))
        .unwrap_or_default();
    let mut devices = vec![super::device(
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
    if let Some(s) = &config.devices.pose_sensor {
        devices.push(super::device(
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
        started_at: super::started_at(epoch_ns),
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
    let clock = Arc::new(VirtualClock::new(epoch_ns));
    let world = Arc::new(Mutex::new(HexapodWorld::new(config, clock.clone())));
    let devices = HexapodDevices {
        hexapod: Box::new(SimHexapod {
            id: config.devices.hexapod.id.clone(),
            world: world.clone(),
        }),
        pose_sensor: config.devices.pose_sensor.as_ref().map(|s| {
            Box::new(SimPoseSensor {
                id: s.id.clone(),
                world: world.clone(),
            }) as Box<dyn geocal_drivers::PoseSensor>
        }),
    };
    super::record_and_solve(
        &session_header(config, epoch_ns),
        clock.as_ref(),
        options,
        |handle| async {
            let sequencer = HexapodSequencer::new(&plan, devices, handle, clock.clone());
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
