//! `geocal monitor --device SPEC`: one device through its real driver, its readings printed
//! live (rate-limited) and, with `--out`, recorded as a session of kind `monitor`.
//!
//! Values are SI in the session and on screen (with a human unit beside them). Driver
//! settings come from an optional TOML file (`[hpi3d]`, `[grbl]`, `[rotary]`, `[probe]`, or a
//! run config's `[devices.tracer.hpi3d]` / `[devices.machine.grbl]`), else the drivers' defaults.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use geocal_drivers::grbl::codec::PosFrame;
use geocal_drivers::grbl::{GrblConfig, GrblMachine};
use geocal_drivers::hpi3d::{Hpi3dConfig, Hpi3dTracer};
use geocal_drivers::linuxcnc::{LinuxCncConfig, LinuxCncMachine, ProgramStatus};
use geocal_drivers::modbus_table::{ModbusTable, ModbusTableConfig, RegisterMap};
use geocal_drivers::probe::{AsciiProbe, ProbeConfig};
use geocal_drivers::{DeviceError, Environment, Machine, Probe, RotaryState, RotaryTable, Tracer};
use serde::de::DeserializeOwned;

use crate::clock::system_now_ns;
use crate::session::messages::{
    DeviceInfo, EnvSample, MachineInfo, MachineStateSample, ProbeSample, RotaryStateSample,
    SessionHeader, TracerSample, SESSION_FORMAT,
};
use crate::session::recorder::{RecordStats, Recorder, RecorderHandle, RecorderOptions};

pub const KIND: &str = "monitor";

/// Which device, and where: `KIND:PORT`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum DeviceSpec {
    Hpi3d {
        port: String,
    },
    Grbl {
        port: String,
    },
    /// LinuxCNC's linuxcncrsh at `host:port` (port 5007 when left out).
    Linuxcnc {
        host: String,
        port: u16,
    },
    ModbusTcp {
        address: SocketAddr,
    },
    ModbusRtu {
        port: String,
    },
    Probe {
        port: String,
    },
}

const SPEC_HELP: &str = "expected KIND:WHERE with KIND one of hpi3d, grbl, probe, modbus-rtu \
    (WHERE a serial port, e.g. hpi3d:/dev/ttyUSB0), modbus-tcp (WHERE host:port, e.g. \
    modbus-tcp:127.0.0.1:502) or linuxcnc (WHERE host[:port], e.g. linuxcnc:127.0.0.1:5007)";

impl FromStr for DeviceSpec {
    type Err = anyhow::Error;

    fn from_str(spec: &str) -> anyhow::Result<Self> {
        let Some((kind, place)) = spec.split_once(':') else {
            bail!("device spec `{spec}`: no `:`; {SPEC_HELP}");
        };
        if place.is_empty() {
            bail!("device spec `{spec}`: nothing after `{kind}:`; {SPEC_HELP}");
        }
        let port = place.to_string();
        Ok(match kind {
            "hpi3d" => DeviceSpec::Hpi3d { port },
            "grbl" => DeviceSpec::Grbl { port },
            "probe" => DeviceSpec::Probe { port },
            "modbus-rtu" => DeviceSpec::ModbusRtu { port },
            "linuxcnc" => {
                let (host, port) = match place.rsplit_once(':') {
                    Some((host, port)) => (
                        host,
                        port.parse().map_err(|e| {
                            anyhow::anyhow!(
                                "device spec `{spec}`: `{port}` is not a port number ({e}); \
                                 {SPEC_HELP}"
                            )
                        })?,
                    ),
                    None => (place, 5007),
                };
                if host.is_empty() {
                    bail!("device spec `{spec}`: no host; {SPEC_HELP}");
                }
                DeviceSpec::Linuxcnc {
                    host: host.to_string(),
                    port,
                }
            }
            "modbus-tcp" => DeviceSpec::ModbusTcp {
                address: place.parse().map_err(|e| {
                    anyhow::anyhow!(
                        "device spec `{spec}`: `{place}` is not an IP address and port ({e}); \
                         {SPEC_HELP}"
                    )
                })?,
            },
            other => bail!("device spec `{spec}`: unknown device kind `{other}`; {SPEC_HELP}"),
        })
    }
}

impl DeviceSpec {
    fn kind(&self) -> &'static str {
        match self {
            DeviceSpec::Hpi3d { .. } => "hpi3d",
            DeviceSpec::Grbl { .. } => "grbl",
            DeviceSpec::Linuxcnc { .. } => "linuxcnc",
            DeviceSpec::ModbusTcp { .. } => "modbus-tcp",
            DeviceSpec::ModbusRtu { .. } => "modbus-rtu",
            DeviceSpec::Probe { .. } => "probe",
        }
    }

    fn place(&self) -> String {
        match self {
            DeviceSpec::Hpi3d { port }
            | DeviceSpec::Grbl { port }
            | DeviceSpec::ModbusRtu { port }
            | DeviceSpec::Probe { port } => port.clone(),
            DeviceSpec::ModbusTcp { address } => address.to_string(),
            DeviceSpec::Linuxcnc { host, port } => format!("{host}:{port}"),
        }
    }
}

pub struct MonitorOptions {
    pub device: DeviceSpec,
    /// Stop after this long; None: until Ctrl-C.
    pub seconds: Option<f64>,
    /// Record the readings as a session here.
    pub out: Option<PathBuf>,
    /// Driver settings (TOML).
    pub config: Option<PathBuf>,
    /// At most one printed line per this many seconds (the latest reading).
    pub print_interval_s: f64,
}

#[derive(Debug, Clone, Default, PartialEq)]
pub struct MonitorSummary {
    /// Readings recorded (and seen), by topic kind: `tracer`, `env`, `machine`, `rotary`, `probe`.
    pub readings: BTreeMap<String, u64>,
    /// Device errors met and survived (timeouts, protocol errors).
    pub errors: u64,
    pub stats: Option<RecordStats>,
}

/// The settings table for a device from a TOML file: the first of `paths` present.
fn settings<T: DeserializeOwned>(file: Option<&Path>, paths: &[&str]) -> anyhow::Result<Option<T>> {
    let Some(file) = file else { return Ok(None) };
    let text = std::fs::read_to_string(file)
        .with_context(|| format!("{}: cannot read", file.display()))?;
    let doc: toml::Table = toml::from_str(&text).map_err(|e| {
        anyhow::anyhow!(
            "{}: {}",
            file.display(),
            crate::config::kind_config::toml_error_text(&text, &e)
        )
    })?;
    for path in paths {
        let mut node = Some(&doc);
        let mut value = None;
        for (i, key) in path.split('.').enumerate() {
            let Some(table) = node else { break };
            match table.get(key) {
                Some(toml::Value::Table(t)) if i + 1 < path.split('.').count() => node = Some(t),
                Some(v) if i + 1 == path.split('.').count() => value = Some(v.clone()),
                _ => {
                    node = None;
                }
            }
        }
        if let Some(v) = value {
            let parsed: T = serde_path_to_error::deserialize(v).map_err(|e| {
                anyhow::anyhow!(
                    "{}: key `{path}.{}`: {}",
                    file.display(),
                    e.path(),
                    e.inner()
                )
            })?;
            return Ok(Some(parsed));
        }
    }
    Ok(None)
}

/// The register map used when no `[rotary.map]` is given: the example of
/// docs/protocols/modbus-table.md (32-bit big-endian angles at 100/200, status at 300).
pub fn default_register_map() -> RegisterMap {
    let map = serde_json::json!({
        "unit_id": 1,
        "target": {"address": 100, "width_bits": 32, "word_order": "big", "signed": true,
                    "counts_per_rad": 57295.779513},
        "actual": {"address": 200, "kind": "input", "width_bits": 32, "word_order": "big",
                    "signed": true, "counts_per_rad": 57295.779513},
        "status": {"address": 300, "kind": "input", "in_position_bit": 0, "moving_bit": 1,
                    "fault_bit": 2},
        "command": {"address": 110, "go_value": 1, "clear_value": 0},
        "ack": {"bit": 3},
        "fault_code": {"address": 301, "kind": "input"}
    });
    // A constant that parses: covered by a unit test.
    serde_json::from_value(map).unwrap_or_else(|e| panic!("default register map: {e}"))
}

/// What the loop records and prints.
struct Sink {
    recorder: Option<RecorderHandle>,
    started: Instant,
    print_every: Duration,
    last_print: Option<Instant>,
    summary: MonitorSummary,
}

impl Sink {
    fn t_s(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }

    fn count(&mut self, kind: &str) {
        *self.summary.readings.entry(kind.to_string()).or_insert(0) += 1;
    }

    /// Print `line` unless a line was printed less than `print_every` ago.
    fn print(&mut self, line: impl FnOnce() -> String) -> std::io::Result<()> {
        let now = Instant::now();
        if self
            .last_print
            .is_some_and(|t| now.duration_since(t) < self.print_every)
        {
            return Ok(());
        }
        self.last_print = Some(now);
        crate::console::write_out(format_args!("{}\n", line()))
    }

    /// A device error: survived (printed, counted) unless the link is gone.
    fn error(&mut self, e: DeviceError) -> anyhow::Result<()> {
        match e {
            DeviceError::Timeout { .. } | DeviceError::Protocol { .. } => {
                self.summary.errors += 1;
                crate::console::write_err(format_args!("warning: {e}\n"));
                Ok(())
            }
            other => Err(other.into()),
        }
    }
}

fn header(spec: &DeviceSpec, id: &str, device_kind: &str, axes: Vec<String>) -> SessionHeader {
    let now = system_now_ns();
    let started_at = time::OffsetDateTime::from_unix_timestamp_nanos(now as i128)
        .ok()
        .and_then(|t| {
            t.format(&time::format_description::well_known::Rfc3339)
                .ok()
        })
        .unwrap_or_default();
    let place_key = match spec {
        DeviceSpec::ModbusTcp { .. } | DeviceSpec::Linuxcnc { .. } => "address",
        _ => "port",
    };
    SessionHeader {
        format: SESSION_FORMAT.into(),
        session_id: format!("{KIND}-{}-{}", spec.kind(), now / 1_000_000),
        started_at,
        kind: KIND.into(),
        machine: MachineInfo {
            name: String::new(),
            structure: String::new(),
            axes,
            travel_m: BTreeMap::new(),
            targets: Vec::new(),
        },
        devices: vec![DeviceInfo {
            id: id.into(),
            kind: device_kind.into(),
            driver: spec.kind().into(),
            noise_m: None,
            noise_ppm: None,
            dead_path_m: None,
            wavelength_m: None,
            compensated: None,
            extra: BTreeMap::from([(place_key.to_string(), spec.place().into())]),
        }],
        plan: serde_json::json!({}),
    }
}

/// Connect, read until `seconds` have passed or Ctrl-C, record and print.
pub fn monitor(options: &MonitorOptions) -> anyhow::Result<MonitorSummary> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let recorder = match &options.out {
        Some(path) => {
            if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
                std::fs::create_dir_all(dir)
                    .with_context(|| format!("creating {}", dir.display()))?;
            }
            Some(
                Recorder::create(path, RecorderOptions::default())
                    .with_context(|| format!("creating {}", path.display()))?,
            )
        }
        None => None,
    };
    let mut sink = Sink {
        recorder: recorder.as_ref().map(Recorder::handle),
        started: Instant::now(),
        print_every: Duration::from_secs_f64(options.print_interval_s.max(0.0)),
        last_print: None,
        summary: MonitorSummary::default(),
    };
    let run = runtime.block_on(async {
        let deadline = options
            .seconds
            .map(|s| tokio::time::Instant::now() + Duration::from_secs_f64(s.max(0.0)));
        let until = async move {
            match deadline {
                Some(d) => tokio::time::sleep_until(d).await,
                None => {
                    let _ = tokio::signal::ctrl_c().await;
                }
            }
        };
        tokio::select! {
            r = read_device(options, &mut sink) => r,
            _ = until => Ok(()),
        }
    });
    // Finish the file whatever happened: every reading so far stays readable.
    let stats = match recorder {
        Some(r) => Some(r.finish().context("finishing the session file")?),
        None => None,
    };
    let mut summary = sink.summary;
    summary.stats = stats;
    run.with_context(|| {
        format!(
            "monitoring {}:{}",
            options.device.kind(),
            options.device.place()
        )
    })?;
    Ok(summary)
}

async fn read_device(options: &MonitorOptions, sink: &mut Sink) -> anyhow::Result<()> {
    let file = options.config.as_deref();
    match &options.device {
        DeviceSpec::Hpi3d { port } => {
            let mut cfg: Hpi3dConfig =
                settings(file, &["hpi3d", "devices.tracer.hpi3d"])?.unwrap_or_default();
            cfg.port = port.clone();
            cfg.meteo = true;
            let spec = &options.device;
            let mut tracer = Hpi3dTracer::open(cfg).await?;
            let mut env = tracer.environment();
            let id = tracer.id().to_string();
            if let Some(r) = &sink.recorder {
                r.session(&header(spec, &id, "tracer", Vec::new()), system_now_ns());
            }
            loop {
                match tracer.next_sample().await {
                    Ok(s) => {
                        let sample = TracerSample {
                            seq: s.seq,
                            t_s: s.t_s,
                            length_m: s.length_m,
                            signal: s.signal,
                            tracking: s.tracking,
                            beam_segment: s.beam_segment,
                        };
                        if let Some(r) = &sink.recorder {
                            r.tracer(&id, &sample, system_now_ns());
                        }
                        sink.count("tracer");
                        sink.print(|| {
                            format!(
                                "t {:9.3} s  {id}  length {:.9} m ({:+.6} mm)  signal {:.2}  {}  segment {}",
                                s.t_s,
                                s.length_m,
                                s.length_m * 1e3,
                                s.signal,
                                if s.tracking { "tracking" } else { "BEAM BROKEN" },
                                s.beam_segment
                            )
                        })?;
                    }
                    Err(e) => sink.error(e)?,
                }
                for m in env.poll().await.unwrap_or_default() {
                    let sample = EnvSample {
                        t_s: m.t_s,
                        air_temp_k: m.air_temp_k,
                        pressure_pa: m.pressure_pa,
                        humidity_pct: m.humidity_pct,
                        material_temp_k: m.material_temp_k,
                    };
                    if let Some(r) = &sink.recorder {
                        r.env(env.id(), &sample, system_now_ns());
                    }
                    sink.count("env");
                    // Meteo is slow: every reading is printed.
                    crate::console::write_out(format_args!(
                        "t {:9.3} s  {}  air {:.3} K ({:.2} °C)  pressure {:.0} Pa ({:.2} hPa)  humidity {:.1} %\n",
                        m.t_s,
                        env.id(),
                        m.air_temp_k,
                        m.air_temp_k - 273.15,
                        m.pressure_pa,
                        m.pressure_pa / 100.0,
                        m.humidity_pct
                    ))?;
                }
            }
        }
        DeviceSpec::Grbl { port } => {
            let mut cfg: GrblConfig =
                settings(file, &["grbl", "devices.machine.grbl"])?.unwrap_or_default();
            cfg.port = port.clone();
            let interval = Duration::from_secs_f64(cfg.status_interval_s.max(0.001));
            let mut machine = GrblMachine::open(cfg)?;
            let id = machine.id().to_string();
            if let Some(r) = &sink.recorder {
                let axes = ["x", "y", "z"].map(String::from).to_vec();
                r.session(
                    &header(&options.device, &id, "machine", axes),
                    system_now_ns(),
                );
            }
            let mut seen = 0;
            loop {
                if let Err(e) = machine.state().await {
                    // An Alarm state is a reading here, not a failure: its report is kept.
                    let alarm = machine
                        .last_status()
                        .is_some_and(|s| s.state.as_str() == "Alarm");
                    if !alarm {
                        sink.error(e)?;
                    }
                }
                if machine.status_queries() != seen {
                    seen = machine.status_queries();
                    if let Some(s) = machine.last_status().cloned() {
                        let sample = MachineStateSample {
                            t_s: sink.t_s(),
                            state: s.state.as_str().to_string(),
                            position_m: s.position_m,
                            frame: match s.frame {
                                PosFrame::Machine => "machine".into(),
                                PosFrame::Work => "work".into(),
                            },
                            feed_m_s: s.feed_m_s,
                        };
                        if let Some(r) = &sink.recorder {
                            r.machine_state(&id, &sample, system_now_ns());
                        }
                        sink.count("machine");
                        sink.print(|| {
                            let p = sample.position_m;
                            format!(
                                "t {:9.3} s  {id}  {}  {} position [{:.6}, {:.6}, {:.6}] m ([{:.3}, {:.3}, {:.3}] mm)",
                                sample.t_s,
                                sample.state,
                                sample.frame,
                                p[0],
                                p[1],
                                p[2],
                                p[0] * 1e3,
                                p[1] * 1e3,
                                p[2] * 1e3
                            )
                        })?;
                    }
                }
                tokio::time::sleep(interval).await;
            }
        }
        DeviceSpec::Linuxcnc { host, port } => {
            let mut cfg: LinuxCncConfig =
                settings(file, &["linuxcnc", "devices.machine.linuxcnc"])?.unwrap_or_default();
            cfg.host = host.clone();
            cfg.port = *port;
            let interval = Duration::from_secs_f64(cfg.status_interval_s.max(0.001));
            let connector = geocal_drivers::linuxcnc::tcp_connector(host, *port);
            let mut machine = LinuxCncMachine::observe_with(cfg, connector).await?;
            let id = machine.id().to_string();
            if let Some(r) = &sink.recorder {
                let axes = ["x", "y", "z"].map(String::from).to_vec();
                r.session(
                    &header(&options.device, &id, "machine", axes),
                    system_now_ns(),
                );
            }
            loop {
                match machine.status().await {
                    Err(e) => sink.error(e)?,
                    Ok(s) => {
                        let state = if s.estop {
                            "Estop"
                        } else if !s.machine_on {
                            "Off"
                        } else {
                            match s.program {
                                ProgramStatus::Idle => "Idle",
                                ProgramStatus::Running => "Run",
                                ProgramStatus::Paused => "Hold",
                            }
                        };
                        let sample = MachineStateSample {
                            t_s: sink.t_s(),
                            state: state.into(),
                            position_m: s.position_m,
                            frame: "machine".into(),
                            feed_m_s: None,
                        };
                        if let Some(r) = &sink.recorder {
                            r.machine_state(&id, &sample, system_now_ns());
                        }
                        sink.count("machine");
                        sink.print(|| {
                            let p = sample.position_m;
                            format!(
                                "t {:9.3} s  {id}  {}  machine position [{:.6}, {:.6}, {:.6}] m ([{:.3}, {:.3}, {:.3}] mm)",
                                sample.t_s,
                                sample.state,
                                p[0],
                                p[1],
                                p[2],
                                p[0] * 1e3,
                                p[1] * 1e3,
                                p[2] * 1e3
                            )
                        })?;
                    }
                }
                tokio::time::sleep(interval).await;
            }
        }
        DeviceSpec::ModbusTcp { .. } | DeviceSpec::ModbusRtu { .. } => {
            let mut cfg: ModbusTableConfig = settings(file, &["rotary", "modbus"])?
                .unwrap_or_else(|| ModbusTableConfig::new(default_register_map()));
            let interval = Duration::from_secs_f64(cfg.poll_interval_s.max(0.001));
            let mut table = match &options.device {
                DeviceSpec::ModbusTcp { address } => {
                    cfg.transport = None;
                    ModbusTable::connect_tcp(*address, cfg).await?
                }
                DeviceSpec::ModbusRtu { port } => {
                    let baud = match &cfg.transport {
                        Some(geocal_drivers::modbus_table::ModbusTransport::Rtu {
                            baud, ..
                        }) => *baud,
                        _ => 19_200,
                    };
                    ModbusTable::open_rtu(port, baud, cfg).await?
                }
                _ => unreachable!("matched above"),
            };
            let id = table.id().to_string();
            if let Some(r) = &sink.recorder {
                r.session(
                    &header(&options.device, &id, "rotary_table", Vec::new()),
                    system_now_ns(),
                );
            }
            loop {
                let reading = async {
                    let state = table.state().await?;
                    let encoder_rad = table.read_encoder_rad().await?;
                    let target_rad = table.read_target_rad().await?;
                    Ok::<_, DeviceError>((state, encoder_rad, target_rad))
                }
                .await;
                match reading {
                    Ok((state, encoder_rad, commanded_rad)) => {
                        let sample = RotaryStateSample {
                            t_s: sink.t_s(),
                            commanded_rad,
                            encoder_rad: Some(encoder_rad),
                            in_position: matches!(state, RotaryState::InPosition { .. }),
                        };
                        if let Some(r) = &sink.recorder {
                            r.rotary(&id, &sample, system_now_ns());
                        }
                        sink.count("rotary");
                        sink.print(|| {
                            format!(
                                "t {:9.3} s  {id}  encoder {:.7} rad ({:.5}°)  target {:.7} rad ({:.5}°)  {}",
                                sample.t_s,
                                encoder_rad,
                                encoder_rad.to_degrees(),
                                commanded_rad,
                                commanded_rad.to_degrees(),
                                if sample.in_position { "in position" } else { "moving" }
                            )
                        })?;
                    }
                    Err(e) => sink.error(e)?,
                }
                tokio::time::sleep(interval).await;
            }
        }
        DeviceSpec::Probe { port } => {
            let mut cfg: ProbeConfig =
                settings(file, &["probe", "devices.probe"])?.unwrap_or_default();
            cfg.port = port.clone();
            let mut probe = AsciiProbe::open(cfg)?;
            let id = probe.id().to_string();
            let mut readings: u64 = 0;
            if let Some(r) = &sink.recorder {
                r.session(
                    &header(&options.device, &id, "probe", Vec::new()),
                    system_now_ns(),
                );
            }
            loop {
                match probe.read().await {
                    Ok(p) => {
                        readings += 1;
                        let sample = ProbeSample {
                            seq: readings,
                            t_s: p.t_s,
                            value_m: Some(p.value_m),
                        };
                        if let Some(r) = &sink.recorder {
                            r.probe(&id, &sample, system_now_ns());
                        }
                        sink.count("probe");
                        sink.print(|| {
                            format!(
                                "t {:9.3} s  {id}  {:.9} m ({:+.4} mm)",
                                p.t_s,
                                p.value_m,
                                p.value_m * 1e3
                            )
                        })?;
                    }
                    Err(e) => sink.error(e)?,
                }
                tokio::time::sleep(PROBE_PERIOD).await;
            }
        }
    }
}

/// Pause between two probe requests (a sensor read as fast as it answers would flood the log).
const PROBE_PERIOD: Duration = Duration::from_millis(10);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn specs_parse_or_say_what_was_expected() {
        assert_eq!(
            "hpi3d:/dev/ttyUSB0".parse::<DeviceSpec>().expect("spec"),
            DeviceSpec::Hpi3d {
                port: "/dev/ttyUSB0".into()
            }
        );
        assert_eq!(
            "modbus-tcp:127.0.0.1:502"
                .parse::<DeviceSpec>()
                .expect("spec"),
            DeviceSpec::ModbusTcp {
                address: "127.0.0.1:502".parse().expect("addr")
            }
        );
        assert_eq!(
            "linuxcnc:cnc-pc".parse::<DeviceSpec>().expect("spec"),
            DeviceSpec::Linuxcnc {
                host: "cnc-pc".into(),
                port: 5007
            }
        );
        assert_eq!(
            "linuxcnc:127.0.0.1:5008"
                .parse::<DeviceSpec>()
                .expect("spec"),
            DeviceSpec::Linuxcnc {
                host: "127.0.0.1".into(),
                port: 5008
            }
        );
        for bad in [
            "hpi3d",
            "laser:/dev/x",
            "grbl:",
            "modbus-tcp:localhost",
            "linuxcnc:host:port",
            "linuxcnc::5007",
        ] {
            let err = bad.parse::<DeviceSpec>().expect_err(bad).to_string();
            assert!(
                err.contains(bad) && err.contains("expected KIND:WHERE"),
                "{err}"
            );
        }
    }

    #[test]
    fn the_default_register_map_is_valid() {
        assert_eq!(default_register_map().validate(), Ok(()));
    }

    #[test]
    fn settings_come_from_either_table_and_name_bad_keys() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("m.toml");
        std::fs::write(
            &path,
            "[devices.machine.grbl]\nport = \"\"\nstatus_interval_s = 0.01\n",
        )
        .expect("write");
        let g: GrblConfig = settings(Some(&path), &["grbl", "devices.machine.grbl"])
            .expect("parse")
            .expect("found");
        assert_eq!(g.status_interval_s, 0.01);
        std::fs::write(&path, "[probe]\nport = \"\"\nscale = 2\n").expect("write");
        let err = settings::<ProbeConfig>(Some(&path), &["probe"])
            .expect_err("unknown key")
            .to_string();
        assert!(err.contains("m.toml") && err.contains("probe"), "{err}");
        let none: Option<ProbeConfig> = settings(None, &["probe"]).expect("no file");
        assert!(none.is_none());
    }
}
