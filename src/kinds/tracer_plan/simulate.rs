//! `geocal simulate CONFIG`: hosts the configured device emulators backed by the simulated
//! world for a run driven from another process, and an operator command channel on stdin.
//!
//! stdout: one line per device (`<kind> <id> <driver> <endpoint>`, or with `--json` one JSON
//! object `{"devices": [...]}`), then acknowledgements of the operator's commands read from
//! stdin: `station <id>` (the tracer now stands on that station), `target <id>` (that
//! reflector is mounted), answered `ok station <id>` / `ok target <id>` or `error: ...`.
//! Runs until SIGINT or SIGTERM; writes the truth (`--truth`) at start and again at exit.

use std::io::{BufRead, Write};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use anyhow::Context;
use geocal_drivers::Operator;
use serde::Serialize;
use tokio::sync::mpsc;

use crate::clock::{system_now_ns, VirtualClock};
use crate::config::{Config, DriverKind, HilConfig};
use crate::plan::Plan;
use crate::sim::devices::SharedWorld;
use crate::sim::hil::{HilOperator, HilTime};
use crate::sim::world::SimWorld;

pub struct SimulateOptions {
    /// Write the simulated truth here (at start, and again at exit).
    pub truth: Option<PathBuf>,
    /// Print the device list as one JSON object.
    pub json: bool,
}

/// One hosted device as printed.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct HostedDevice {
    pub kind: String,
    pub id: String,
    pub driver: String,
    /// Pty path, link path or `127.0.0.1:PORT`.
    pub endpoint: String,
}

/// Host the emulators until SIGINT/SIGTERM.
pub fn simulate(config: &Config, options: &SimulateOptions) -> anyhow::Result<()> {
    let sim = config.sim.as_ref().context(
        "geocal simulate needs a [sim] table: the emulators are backed by the simulated world",
    )?;
    if config.devices.tracer.driver != DriverKind::Hpi3d {
        anyhow::bail!(
            "devices.tracer.driver = \"{}\": geocal simulate hosts the HPI-3D emulator, expected \"hpi3d\"",
            config.devices.tracer.driver.as_str()
        );
    }
    if config.devices.machine.driver != DriverKind::Grbl {
        anyhow::bail!(
            "devices.machine.driver = \"{}\": geocal simulate hosts the GRBL emulator, expected \"grbl\"",
            config.devices.machine.driver.as_str()
        );
    }
    let hil: HilConfig = match &config.hil {
        Some(h) => h.clone(),
        None => serde_json::from_str("{}").context("default [hil] settings")?,
    };
    let plan = Plan::from_config(config);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    runtime.block_on(async {
        let epoch_ns = system_now_ns();
        let time = Arc::new(HilTime::new(epoch_ns));
        let world: SharedWorld = Arc::new(Mutex::new(SimWorld::new(
            config,
            &plan,
            Arc::new(VirtualClock::new(epoch_ns)),
        )?));
        let hosted = crate::devices::hosting::host(config, sim, &hil, &world, &time).await?;
        let mut devices = vec![HostedDevice {
            kind: "tracer".into(),
            id: config.devices.tracer.id.clone(),
            driver: "hpi3d".into(),
            endpoint: hosted.tracer_path.clone(),
        }];
        if let Some(path) = &hosted.machine_path {
            devices.push(HostedDevice {
                kind: "machine".into(),
                id: config.devices.machine.id.clone(),
                driver: "grbl".into(),
                endpoint: path.clone(),
            });
        }
        if let (Some(table), Some(t)) = (&hosted.table, &config.devices.rotary_table) {
            devices.push(HostedDevice {
                kind: "rotary_table".into(),
                id: t.id.clone(),
                driver: table.driver.as_str().into(),
                endpoint: table.endpoint.clone(),
            });
        }
        let mut out = std::io::stdout();
        if options.json {
            writeln!(out, "{}", serde_json::json!({ "devices": devices }))?;
        } else {
            for d in &devices {
                writeln!(out, "{} {} {} {}", d.kind, d.id, d.driver, d.endpoint)?;
            }
            writeln!(out, "ready")?;
        }
        out.flush()?;
        write_truth(options, &world, config, &plan)?;

        let mut operator = HilOperator {
            world: world.clone(),
            time: time.clone(),
        };
        let mut commands = stdin_lines();
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
            .context("listening for SIGTERM")?;
        let mut stdin_open = true;
        loop {
            tokio::select! {
                _ = tokio::signal::ctrl_c() => break,
                _ = term.recv() => break,
                line = commands.recv(), if stdin_open => match line {
                    Some(line) => {
                        let reply = command(&mut operator, config, &plan, line.trim()).await;
                        writeln!(out, "{reply}")?;
                        out.flush()?;
                    }
                    // No more commands; keep serving until stopped.
                    None => stdin_open = false,
                },
            }
        }
        write_truth(options, &world, config, &plan)?;
        drop(hosted);
        Ok(())
    })
}

fn write_truth(
    options: &SimulateOptions,
    world: &SharedWorld,
    config: &Config,
    plan: &Plan,
) -> anyhow::Result<()> {
    let Some(path) = &options.truth else {
        return Ok(());
    };
    let truth = {
        let w = world
            .lock()
            .map_err(|_| anyhow::anyhow!("simulated world poisoned"))?;
        w.truth(config, plan)
    };
    std::fs::write(path, serde_json::to_string_pretty(&truth)?)
        .with_context(|| format!("writing truth to {}", path.display()))
}

/// Lines of stdin, read on a thread of its own.
fn stdin_lines() -> mpsc::UnboundedReceiver<String> {
    let (tx, rx) = mpsc::unbounded_channel();
    std::thread::spawn(move || {
        for line in std::io::stdin().lock().lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

/// Carry out one operator command; the reply line.
async fn command(operator: &mut HilOperator, config: &Config, plan: &Plan, line: &str) -> String {
    let mut words = line.split_whitespace();
    match (words.next(), words.next(), words.next()) {
        (None, ..) => "error: empty command; expected `station <id>` or `target <id>`".into(),
        (Some("station"), Some(id), None) => {
            let Some(index) = plan.stations.iter().position(|s| s.id == id) else {
                let ids: Vec<&str> = plan.stations.iter().map(|s| s.id.as_str()).collect();
                return format!(
                    "error: unknown station `{id}`; expected one of {}",
                    ids.join(", ")
                );
            };
            match operator
                .place_station(index, id, plan.stations[index].hint_m)
                .await
            {
                Ok(()) => format!("ok station {id}"),
                Err(e) => format!("error: {e}"),
            }
        }
        (Some("target"), Some(id), None) => match config.target_offset(id) {
            Some(offset_m) => match operator.mount_target(id, offset_m).await {
                Ok(()) => format!("ok target {id}"),
                Err(e) => format!("error: {e}"),
            },
            None => format!("error: unknown target `{id}` (machine.targets)"),
        },
        _ => format!("error: cannot read `{line}`; expected `station <id>` or `target <id>`"),
    }
}
