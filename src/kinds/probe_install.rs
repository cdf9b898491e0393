//! A whole simulated `probe_install` run: the CMM and the laser probe of the simulated world,
//! the kind's sequencer, the recording, the truth export and the solve of the recorded file.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use crate::clock::{system_now_ns, VirtualClock};
use crate::config::probe_install::{ProbeInstallConfig, KIND};
use crate::plan::probe_install::{ProbeInstallPlan, CMM_AXES};
use crate::run::{RunOptions, RunOutput};
use crate::sequencer::probe_install::{ProbeInstallDevices, ProbeInstallSequencer};
use crate::session::messages::{MachineInfo, SessionHeader, SESSION_FORMAT};
use crate::sim::probe_install::{ProbeInstallWorld, SimCmm, SimLaserProbe};

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
        started_at: super::started_at(epoch_ns),
        kind: KIND.into(),
        machine: MachineInfo {
            name: config.machine.name.clone(),
            structure: "XYZAB".into(),
            axes: CMM_AXES.iter().map(|a| a.to_string()).collect(),
            travel_m: config.machine.travel_m.clone(),
            targets: Vec::new(),
        },
        devices: vec![
            super::device(
                &m.id,
                "machine",
                m.driver.as_str(),
                None,
                BTreeMap::from([
                    ("feed_m_s".into(), m.feed_m_s.into()),
                    ("rotary_speed_rad_s".into(), m.rotary_speed_rad_s.into()),
                ]),
            ),
            super::device(
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
    super::record_and_solve(
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
