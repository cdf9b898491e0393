//! A whole `hexapod` run: the devices (simulated, Modbus emulated under `[hil]`, or real),
//! the kind's sequencer, the recording, the truth export and the solve of the recorded file;
//! and the continuation of an interrupted run (`geocal run --resume`).

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::Context;
use geocal_drivers::PlatformPose;

use crate::clock::system_now_ns;
use crate::kinds::hexapod::config::{HexapodConfig, HexapodDriver, KIND};
use crate::kinds::hexapod::plan::{HexapodPlan, POSE_AXES};
use crate::kinds::hexapod::sequence::HexapodSequencer;
use crate::run::resume::Interruption;
use crate::run::{RunOptions, RunOutput};
use crate::session::messages::{MachineInfo, RunEvent, SessionHeader, SESSION_FORMAT};
use crate::session::reader::Session;

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
    std::fs::create_dir_all(&options.out_dir)
        .with_context(|| format!("creating output directory {}", options.out_dir.display()))?;
    crate::run::resume::store_config(config, &options.out_dir)?;
    execute(config, options, None)
}

/// Where an interrupted run goes on, read from its recording.
struct Continuation {
    interruption: Interruption,
    /// The first pose without `pose_end` (the number of poses: none left).
    pose: usize,
    /// The poses the interrupted run commanded (its `pose_begin`s), in order.
    commanded: Vec<PlatformPose>,
}

/// `geocal run [CONFIG] --resume DIR` of a hexapod run: the poses the interrupted run
/// finished are kept, the run continues at the first unfinished one. The leg encoders are
/// incremental and pose 0 is the reference of every change, so the controller must have kept
/// counting through the interruption (not powered off or homed again).
pub fn resume(
    dir: &Path,
    config: Option<&Path>,
    options: &RunOptions,
) -> anyhow::Result<RunOutput> {
    let (config, interruption) = crate::run::resume::read_interrupted_run(
        dir,
        config,
        KIND,
        |p| Ok(HexapodConfig::load(p)?),
        |c: &HexapodConfig| &c.plan,
    )?;
    let plan = HexapodPlan::from_config(&config);
    let pose = first_unfinished_pose(&plan, &interruption.session);
    let commanded = commanded_poses(&interruption.session);
    tracing::info!(
        kept = interruption.messages_kept(),
        "resuming {} at pose {pose}",
        dir.display()
    );
    let continuation = Continuation {
        interruption,
        pose,
        commanded,
    };
    execute(&config, options, Some(continuation))
}

/// The first pose in plan order without a `pose_end`; the number of poses when every one is
/// finished.
fn first_unfinished_pose(plan: &HexapodPlan, session: &Session) -> usize {
    crate::run::resume::first_unfinished(plan.poses.len(), session, |e| match e {
        RunEvent::PoseEnd { pose } => Some(*pose),
        _ => None,
    })
}

/// The commanded pose of every `pose_begin` with all six coordinates, in order.
fn commanded_poses(session: &Session) -> Vec<PlatformPose> {
    session
        .events
        .iter()
        .filter_map(|e| match &e.msg {
            RunEvent::PoseBegin { axes, .. } => {
                let v: Option<Vec<f64>> = POSE_AXES.iter().map(|a| axes.get(a).copied()).collect();
                let v = v?;
                Some(PlatformPose {
                    translation_m: [v[0], v[1], v[2]],
                    rotation_vector_rad: [v[3], v[4], v[5]],
                })
            }
            _ => None,
        })
        .collect()
}

/// A run from the start, or the continuation of an interrupted one at a pose.
fn execute(
    config: &HexapodConfig,
    options: &RunOptions,
    mut continuation: Option<Continuation>,
) -> anyhow::Result<RunOutput> {
    let plan = HexapodPlan::from_config(config);
    // Simulated: the sim hexapod in virtual time (the pose sensor is the world's or `given`).
    let simulated = config.devices.hexapod.driver == HexapodDriver::Sim;
    let epoch_ns = continuation
        .as_ref()
        .map_or_else(system_now_ns, |c| c.interruption.epoch_ns(simulated));
    let runtime = crate::run::run_runtime(&options.control, config.sim.is_none())?;
    let built = runtime.block_on(super::devices::build(
        config,
        epoch_ns,
        options.control.devices.as_deref(),
    ))?;
    if let Some(c) = continuation.as_mut() {
        if !simulated {
            c.interruption.wait_for_clock(built.clock.as_ref())?;
        }
        c.interruption.set_aside()?;
    }
    let (session_path, recorder) = crate::run::create_session(options)?;
    let handle = recorder.handle();
    let mut interruption = None;
    let mut first_pose = 0;
    match continuation {
        Some(mut c) => {
            if let (Some(world), Some(sim)) = (&built.world, &config.sim) {
                let (t_s, noise_seed) = c.interruption.simulated_restart(sim.seed);
                world
                    .lock()
                    .map_err(|_| anyhow::anyhow!("simulated world poisoned"))?
                    .resume_at(simulated.then_some(t_s), noise_seed, &c.commanded);
            }
            let event = RunEvent::Resume {
                resume_index: c.interruption.resume_index,
                messages_kept: c.interruption.messages_kept(),
                station: None,
                target: None,
                pass: None,
                point: None,
                height_index: None,
                angle_index: None,
                posture: None,
                pose: (c.pose < plan.poses.len()).then_some(c.pose),
            };
            c.interruption
                .record_copy(&handle, event, built.clock.as_ref());
            first_pose = c.pose;
            interruption = Some(c.interruption);
        }
        None => handle.session(&session_header(config, epoch_ns), built.clock.now_ns()),
    }
    let poll_s = config
        .devices
        .hexapod
        .modbus
        .as_ref()
        .map_or(0.0, |m| m.poll_interval_s);
    let sequencer = HexapodSequencer::new(&plan, built.devices, handle, built.clock.clone())
        .with_poll_interval(poll_s)
        .resume_at(first_pose);
    let summary = runtime.block_on(options.control.until_cancelled(
        sequencer.run(&mut |done: u64, total: u64| options.control.report_progress(done, total)),
    ));
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
    crate::kinds::finish_and_solve(
        recorder,
        summary,
        session_path,
        options,
        interruption.as_ref(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `--resume DIR` runs on the configuration stored at run start: it must read back as
    /// the one the run started with.
    #[test]
    fn the_stored_configuration_reads_back_equal() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/config/hexapod.toml");
        let config = HexapodConfig::load(Path::new(path)).expect("example config");
        let dir = tempfile::tempdir().expect("temp dir");
        crate::run::resume::store_config(&config, dir.path()).expect("store");
        let stored = dir.path().join(crate::run::resume::CONFIG_FILE);
        assert_eq!(HexapodConfig::load(&stored).expect("stored config"), config);
    }
}
