//! A whole run of a tracer plan: config -> plan -> devices -> sequencer -> recorded session ->
//! solve -> results. The results come from reading the recorded session back, exactly as
//! `geocal solve` does.

use std::collections::BTreeMap;

use anyhow::Context;

use super::resume::Continuation;
use crate::clock::system_now_ns;
use crate::config::Config;
use crate::kinds::registry::solve_and_write;
use crate::plan::{Plan, AXES};
use crate::run::{create_session, progress_bar, run_runtime, write_truth, RunOptions, RunOutput};
use crate::sequencer::Sequencer;
use crate::session::messages::{
    DeviceInfo, MachineInfo, SessionHeader, TargetInfo, SESSION_FORMAT,
};

pub fn run(config: &Config, options: &RunOptions) -> anyhow::Result<RunOutput> {
    std::fs::create_dir_all(&options.out_dir)
        .with_context(|| format!("creating output directory {}", options.out_dir.display()))?;
    crate::run::resume::store_config(config, &options.out_dir)?;
    execute(config, options, None)
}

/// A run from the start, or the continuation of an interrupted one (src/run/resume.rs).
pub(crate) fn execute(
    config: &Config,
    options: &RunOptions,
    mut continuation: Option<&mut Continuation>,
) -> anyhow::Result<RunOutput> {
    let plan = Plan::from_config(config);
    let epoch_ns = continuation
        .as_ref()
        .map_or_else(system_now_ns, |c| c.epoch_ns(config));
    let runtime = run_runtime(&options.control, crate::devices::uses_real_devices(config))?;
    let mut built = runtime.block_on(crate::devices::build(
        config,
        &plan,
        epoch_ns,
        options.control.operator.as_ref(),
        options.control.devices.as_deref(),
    ))?;
    let prepared = (|| {
        if let Some(c) = continuation.as_deref_mut() {
            c.prepare_world(config, &built)?;
            c.set_aside()?;
        }
        create_session(options)
    })();
    let (session_path, recorder) = match prepared {
        Ok(prepared) => prepared,
        Err(e) => {
            // The run never started: its machine's controller is still left as found.
            if let Err(f) = runtime.block_on(built.devices.machine.finish()) {
                tracing::warn!("leaving the machine's controller as found: {f}");
            }
            return Err(e);
        }
    };
    let handle = recorder.handle();
    let resume_at = match continuation.as_deref_mut() {
        Some(c) => Some(c.record_start(&handle, built.clock.as_ref())),
        None => {
            handle.session(&session_header(config, epoch_ns), built.clock.now_ns());
            None
        }
    };

    let bar = progress_bar(options.progress, "points");
    let mut progress = |done: u64, total: u64| {
        bar.set_length(total);
        bar.set_position(done);
        options.control.report_progress(done, total);
    };
    let mut sequencer = Sequencer::new(&plan, built.devices, handle, built.clock.clone());
    if let Some(at) = resume_at {
        sequencer = sequencer.resume_at(at);
    }
    if config.devices.machine.driver == crate::config::DriverKind::Passive {
        let passive = config.devices.machine.passive.clone().unwrap_or_default();
        sequencer = sequencer.passive(passive.hint_tolerance_m);
    }
    // The sequencer watches the cancellation itself, so that a cancelled run still leaves
    // the machine's controller as found.
    let sequencer = sequencer.cancelled_by(options.control.cancel.clone());
    let summary = runtime.block_on(sequencer.run(&mut progress));
    // Stop the emulators of an emulated run.
    drop(built.emulators);
    bar.finish_and_clear();
    // Finish the file even after a failed run: every recorded sample stays readable.
    let stats = recorder.finish().context("finishing the session file")?;
    let summary = summary.context("run failed (the session recorded so far is kept)")?;
    if let Some(c) = continuation.as_deref() {
        c.finished(&session_path)?;
    }
    tracing::info!(
        samples = summary.samples,
        points = summary.points_measured,
        bytes = stats.bytes,
        "run recorded to {}",
        session_path.display()
    );

    if let (Some(path), Some(world)) = (&options.truth, &built.world) {
        let world = world
            .lock()
            .map_err(|_| anyhow::anyhow!("simulated world poisoned"))?;
        write_truth(path, &world.truth(config, &plan))?;
    }

    let (results, results_path) = solve_and_write(&session_path, options)?;
    Ok(RunOutput {
        session_path,
        results_path,
        summary,
        results,
    })
}

/// What each `[sim] compensation` entry applies, recorded so that the report of a verification
/// run needs neither the table files nor their formats. The configuration's validation loaded
/// every file; one that became unreadable since is recorded by its error.
fn applied_tables(tables: &[crate::config::sim::SimCompensation]) -> Vec<serde_json::Value> {
    tables
        .iter()
        .map(|c| {
            let names = c.machine_axis_names();
            let controller_axis = c.controller_axis_name();
            let applied = c
                .selection(&names, &controller_axis)
                .ok_or_else(|| format!("{}: no axis", c.file.display()))
                .and_then(|selection| {
                    crate::compensate::applied::describe(c.format, &c.file, selection)
                        .map_err(|e| e.to_string())
                });
            match applied {
                Ok(a) => serde_json::to_value(a).unwrap_or_default(),
                Err(e) => serde_json::json!({ "file": c.file, "error": e }),
            }
        })
        .collect()
}

fn session_header(config: &Config, epoch_ns: u64) -> SessionHeader {
    let started_at = crate::session::messages::started_at(epoch_ns);
    let tracer = &config.devices.tracer;
    let mut devices = vec![DeviceInfo {
        id: tracer.id.clone(),
        kind: "tracer".into(),
        driver: tracer.driver.as_str().into(),
        noise_m: Some(tracer.noise_m),
        noise_ppm: Some(tracer.noise_ppm),
        dead_path_m: Some(tracer.dead_path_m),
        wavelength_m: Some(tracer.wavelength_m),
        compensated: Some(tracer.compensated),
        extra: BTreeMap::from([("sample_rate_hz".into(), tracer.sample_rate_hz.into())]),
    }];
    if let Some(env) = &config.devices.environment {
        devices.push(plain_device(&env.id, "environment", env.driver.as_str()));
    }
    let machine = &config.devices.machine;
    let mut machine_device = plain_device(&machine.id, "machine", machine.driver.as_str());
    machine_device
        .extra
        .insert("feed_m_s".into(), machine.feed_m_s.into());
    // A verification run: the controller tables the simulated machine applied.
    if let Some(tables) = config.sim.as_ref().map(|s| &s.compensation) {
        if !tables.is_empty() {
            machine_device.extra.insert(
                "compensation".into(),
                serde_json::to_value(tables).unwrap_or_default(),
            );
            machine_device.extra.insert(
                "compensation_applied".into(),
                serde_json::to_value(applied_tables(tables)).unwrap_or_default(),
            );
        }
    }
    devices.push(machine_device);
    if let Some(table) = &config.devices.rotary_table {
        devices.push(plain_device(
            &table.id,
            "rotary_table",
            table.driver.as_str(),
        ));
    }
    let seed = config
        .sim
        .as_ref()
        .map(|s| format!("-seed{}", s.seed))
        .unwrap_or_default();
    SessionHeader {
        format: SESSION_FORMAT.into(),
        session_id: format!("{}-{}{}", config.kind.as_str(), epoch_ns / 1_000_000, seed),
        started_at,
        kind: config.kind.as_str().into(),
        machine: MachineInfo {
            name: config.machine.name.clone(),
            structure: config.machine.structure.clone(),
            axes: AXES.iter().map(|a| a.to_string()).collect(),
            travel_m: config.machine.travel_m.clone(),
            targets: config
                .machine
                .targets
                .iter()
                .map(|t| TargetInfo {
                    id: t.id.clone(),
                    offset_m: t.offset_m,
                })
                .collect(),
        },
        devices,
        plan: serde_json::to_value(&config.plan).unwrap_or_default(),
    }
}

fn plain_device(id: &str, kind: &str, driver: &str) -> DeviceInfo {
    DeviceInfo {
        id: id.into(),
        kind: kind.into(),
        driver: driver.into(),
        noise_m: None,
        noise_ppm: None,
        dead_path_m: None,
        wavelength_m: None,
        compensated: None,
        extra: BTreeMap::new(),
    }
}
