//! The daemon's configuration (`geocal serve --config FILE`): where it listens, where it keeps
//! its data, its token, limits, which serial ports and hosts job configs may name, the live
//! view's address, and its schedules.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::Deserialize;

pub const DEFAULT_LISTEN: &str = "127.0.0.1:7878";
pub const DEFAULT_LIVE: &str = "127.0.0.1:8765";

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServeConfig {
    /// The HTTP API's address (loopback by default).
    #[serde(default = "default_listen")]
    pub listen: SocketAddr,
    /// Jobs, their files and the catalog.
    #[serde(default = "default_data_dir")]
    pub data_dir: PathBuf,
    /// A file holding the bearer token (required to listen beyond loopback; must not be
    /// group- or world-readable).
    #[serde(default)]
    pub token_file: Option<PathBuf>,
    /// Largest request body accepted, bytes (larger: 413).
    #[serde(default = "default_max_body_bytes")]
    pub max_body_bytes: usize,
    /// The Foxglove WebSocket live view's address; "off" to disable.
    #[serde(default = "default_live")]
    pub live: String,
    /// Web origins, beside the Foxglove app's, allowed to open the live view (e.g.
    /// "https://viewer.example"); clients that send no `Origin` (native ones) are allowed.
    #[serde(default)]
    pub live_origins: Vec<String>,
    /// `Host` names the API answers to, beside the loopback ones, when it runs without a
    /// token (a guard against DNS rebinding; with a token every host is answered).
    #[serde(default)]
    pub allowed_host_names: Vec<String>,
    /// Most API requests handled at once (taken after the Host and token checks); more wait
    /// for a free slot.
    #[serde(default = "default_max_connections")]
    pub max_connections: usize,
    /// Most event streams (`/v1/events`) open at once, apart from the request slots.
    #[serde(default = "default_max_streams")]
    pub max_streams: usize,
    /// Time a client has to send a request's headers, and then its body, seconds.
    #[serde(default = "default_request_timeout_s")]
    pub request_timeout_s: f64,
    /// Serial ports a job's configuration may name (exact paths, or a prefix ending in `*`).
    #[serde(default)]
    pub allowed_ports: Vec<String>,
    /// Hosts (`host` or `host:port`) a job's configuration may name.
    #[serde(default)]
    pub allowed_hosts: Vec<String>,
    /// Folders whose files a submitted plan may name (compensation tables, password files):
    /// every named file must resolve, symlinks followed, inside one. Empty: none.
    #[serde(default)]
    pub allowed_read_dirs: Vec<PathBuf>,
    /// The plan library: a folder of plan configurations the console offers to submit by
    /// name (only `.toml` files directly in it). None: no library.
    #[serde(default)]
    pub plan_library: Option<PathBuf>,
    /// Scheduled jobs.
    #[serde(default)]
    pub schedule: Vec<super::schedule::ScheduleConfig>,
    /// Whether real devices stay connected between jobs.
    #[serde(default)]
    pub devices: DeviceHolding,
    /// The machines' history: comparison after scheduled runs, trends, notifications.
    #[serde(default)]
    pub history: super::machines::HistoryConfig,
    /// Where relative plan paths of the schedules start (the configuration file's folder).
    #[serde(skip)]
    pub base_dir: PathBuf,
}

fn default_listen() -> SocketAddr {
    DEFAULT_LISTEN
        .parse()
        .unwrap_or(SocketAddr::from(([127, 0, 0, 1], 7878)))
}

fn default_data_dir() -> PathBuf {
    PathBuf::from("geocal-data")
}

fn default_max_body_bytes() -> usize {
    1 << 20
}

fn default_max_connections() -> usize {
    64
}

fn default_max_streams() -> usize {
    16
}

fn default_request_timeout_s() -> f64 {
    10.0
}

fn default_live() -> String {
    DEFAULT_LIVE.into()
}

impl Default for ServeConfig {
    fn default() -> Self {
        ServeConfig {
            listen: default_listen(),
            data_dir: default_data_dir(),
            token_file: None,
            max_body_bytes: default_max_body_bytes(),
            live: default_live(),
            live_origins: Vec::new(),
            allowed_host_names: Vec::new(),
            max_connections: default_max_connections(),
            max_streams: default_max_streams(),
            request_timeout_s: default_request_timeout_s(),
            allowed_ports: Vec::new(),
            allowed_hosts: Vec::new(),
            allowed_read_dirs: Vec::new(),
            plan_library: None,
            schedule: Vec::new(),
            devices: DeviceHolding::default(),
            history: Default::default(),
            base_dir: PathBuf::from("."),
        }
    }
}

/// `[devices]`: real devices are connected when a job first needs them and kept open for the
/// next job (simulated and emulated devices belong to their job's world and are not).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeviceHolding {
    /// Keep connections open between jobs (false: every job opens and closes its own).
    #[serde(default = "keep_connections")]
    pub hold: bool,
    /// Close a connection no job has used for this long, seconds (absent: keep it).
    #[serde(default)]
    pub release_idle_after_s: Option<f64>,
}

fn keep_connections() -> bool {
    true
}

impl Default for DeviceHolding {
    fn default() -> Self {
        DeviceHolding {
            hold: keep_connections(),
            release_idle_after_s: None,
        }
    }
}

impl DeviceHolding {
    /// The idle time after which connections close.
    pub fn release_idle_after(&self) -> anyhow::Result<Option<std::time::Duration>> {
        self.release_idle_after_s
            .map(|s| {
                std::time::Duration::try_from_secs_f64(s)
                    .ok()
                    .filter(|d| !d.is_zero())
                    .with_context(|| {
                        format!("devices.release_idle_after_s = {s}: expected a positive number of seconds")
                    })
            })
            .transpose()
    }
}

impl ServeConfig {
    /// `request_timeout_s` as a duration.
    pub fn request_timeout(&self) -> anyhow::Result<std::time::Duration> {
        let s = self.request_timeout_s;
        std::time::Duration::try_from_secs_f64(s)
            .ok()
            .filter(|d| !d.is_zero())
            .with_context(|| {
                format!("request_timeout_s = {s}: expected a positive number of seconds")
            })
    }

    pub fn load(path: &Path) -> anyhow::Result<ServeConfig> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading the daemon configuration {}", path.display()))?;
        let mut config: ServeConfig = crate::config::kind_config::parse_strict(&text, path)?;
        config
            .devices
            .release_idle_after()
            .with_context(|| path.display().to_string())?;
        config
            .request_timeout()
            .with_context(|| path.display().to_string())?;
        for (key, value) in [
            ("max_connections", config.max_connections),
            ("max_streams", config.max_streams),
        ] {
            if value == 0 {
                anyhow::bail!("{}: {key} = 0: expected at least 1", path.display());
            }
        }
        config
            .history
            .check()
            .with_context(|| path.display().to_string())?;
        config.base_dir = path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."))
            .to_owned();
        // Like the schedules' plans, a relative library is the configuration file's neighbour.
        if let Some(library) = &mut config.plan_library {
            if library.is_relative() {
                *library = config.base_dir.join(&*library);
            }
        }
        Ok(config)
    }
}

/// Serial ports and hosts a job's configuration names: every string under `devices` (and
/// `hil`) at a key that names a port or a host.
pub fn named_endpoints(config: &toml::Table) -> Vec<(String, String)> {
    fn walk(key_path: &str, value: &toml::Value, out: &mut Vec<(String, String)>) {
        match value {
            toml::Value::Table(table) => {
                for (key, value) in table {
                    let path = format!("{key_path}.{key}");
                    if let toml::Value::String(text) = value {
                        // An empty port is filled in by a hosted emulator.
                        if ENDPOINT_KEYS.contains(&key.as_str()) && !text.is_empty() {
                            out.push((path.clone(), text.clone()));
                        }
                    }
                    walk(&path, value, out);
                }
            }
            toml::Value::Array(items) => {
                for (i, item) in items.iter().enumerate() {
                    walk(&format!("{key_path}[{i}]"), item, out);
                }
            }
            _ => {}
        }
    }
    let mut out = Vec::new();
    for (key, value) in config {
        walk(key, value, &mut out);
    }
    out
}

const ENDPOINT_KEYS: &[&str] = &["port", "serial_port", "device", "host", "address", "addr"];

/// Files a plan configuration names: every string at a key that names a file (`file`,
/// `*_file`, `*_path`, `*_dir`), wherever it stands. The path keys of every kind today:
/// `sim.compensation[N].file`, `hil.linuxcnc.comp_files[N].file` and
/// `devices.machine.linuxcnc.password_file` (docs/serve.md); the rule also catches any added
/// later under one of these names.
pub fn named_files(config: &toml::Table) -> Vec<(String, String)> {
    fn names_a_file(key: &str) -> bool {
        key == "file"
            || key == "path"
            || ["_file", "_path", "_dir"].iter().any(|s| key.ends_with(s))
    }
    fn walk(key_path: &str, value: &toml::Value, out: &mut Vec<(String, String)>) {
        match value {
            toml::Value::Table(table) => {
                for (key, value) in table {
                    let path = format!("{key_path}.{key}");
                    if let (true, toml::Value::String(text)) = (names_a_file(key), value) {
                        out.push((path.clone(), text.clone()));
                    }
                    walk(&path, value, out);
                }
            }
            toml::Value::Array(items) => {
                for (i, item) in items.iter().enumerate() {
                    walk(&format!("{key_path}[{i}]"), item, out);
                }
            }
            _ => {}
        }
    }
    let mut out = Vec::new();
    for (key, value) in config {
        if let (true, toml::Value::String(text)) = (names_a_file(key), value) {
            out.push((key.clone(), text.clone()));
        }
        walk(key, value, &mut out);
    }
    out
}

/// Where the files a submitted plan names may be: inside `allowed_read_dirs` (resolved,
/// symlinks followed), never the daemon's token file nor anything in its data dir.
#[derive(Debug, Clone, Default)]
pub struct ReadAllowance {
    dirs: Vec<PathBuf>,
    denied_files: Vec<PathBuf>,
    denied_dirs: Vec<PathBuf>,
}

impl ReadAllowance {
    /// The configuration's `allowed_read_dirs`, each of which must exist.
    pub fn of(config: &ServeConfig) -> anyhow::Result<ReadAllowance> {
        let dirs = config
            .allowed_read_dirs
            .iter()
            .enumerate()
            .map(|(i, dir)| {
                std::fs::canonicalize(dir)
                    .ok()
                    .filter(|d| d.is_dir())
                    .with_context(|| {
                        format!(
                            "allowed_read_dirs[{i}] = \"{}\": expected an existing folder",
                            dir.display()
                        )
                    })
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        let resolved = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
        Ok(ReadAllowance {
            dirs,
            denied_files: config.token_file.iter().map(|p| resolved(p)).collect(),
            denied_dirs: vec![resolved(&config.data_dir)],
        })
    }

    /// Every file `plan` names, or an error naming the first key whose file is not allowed.
    /// The error says nothing of the file (whether it exists, what it holds).
    pub fn check(&self, plan: &toml::Table) -> Result<(), String> {
        for (key, value) in named_files(plan) {
            let path = Path::new(&value);
            if !path.is_absolute() {
                return Err(format!(
                    "key `{key}`: \"{value}\" is a relative path: a submitted plan names its \
                     files by absolute path, inside the daemon's allowed_read_dirs"
                ));
            }
            if !self.allows(path) {
                return Err(format!(
                    "key `{key}`: \"{value}\" is not a file this daemon lets a plan read (only \
                     files inside its allowed_read_dirs{})",
                    if self.dirs.is_empty() {
                        ", none configured"
                    } else {
                        ""
                    }
                ));
            }
        }
        Ok(())
    }

    fn allows(&self, path: &Path) -> bool {
        let Ok(resolved) = std::fs::canonicalize(path) else {
            return false;
        };
        resolved.is_file()
            && self.dirs.iter().any(|d| resolved.starts_with(d))
            && !self.denied_files.contains(&resolved)
            && !self.denied_dirs.iter().any(|d| resolved.starts_with(d))
    }
}

/// Whether `value` at `key_path` is allowed: serial ports (paths) against `allowed_ports`,
/// anything else against `allowed_hosts`.
pub fn endpoint_allowed(config: &ServeConfig, value: &str) -> bool {
    let matches = |pattern: &String| match pattern.strip_suffix('*') {
        Some(prefix) => value.starts_with(prefix),
        None => value == pattern,
    };
    if value.starts_with('/') {
        // A prefix pattern must not be left by `..` (`/dev/ttyUSB0/../../etc/shadow`).
        let climbs = Path::new(value)
            .components()
            .any(|c| c == std::path::Component::ParentDir);
        !climbs && config.allowed_ports.iter().any(matches)
    } else {
        let host = value.rsplit_once(':').map_or(value, |(h, _)| h);
        config
            .allowed_hosts
            .iter()
            .any(|p| matches(p) || p.as_str() == host)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_are_found_and_checked_against_the_allow_lists() {
        let plan: toml::Table = toml::from_str(
            r#"
            kind = "multilateration"
            [devices.tracer.hpi3d]
            port = "/dev/ttyUSB0"
            [devices.rotary_table.modbus.transport.tcp]
            host = "192.168.1.20:502"
            [plan]
            port = 3
            "#,
        )
        .unwrap();
        let found = named_endpoints(&plan);
        assert_eq!(
            found,
            vec![
                (
                    "devices.rotary_table.modbus.transport.tcp.host".into(),
                    "192.168.1.20:502".into()
                ),
                ("devices.tracer.hpi3d.port".into(), "/dev/ttyUSB0".into()),
            ]
        );
        let config = ServeConfig {
            allowed_ports: vec!["/dev/ttyUSB*".into()],
            allowed_hosts: vec!["192.168.1.20".into()],
            ..ServeConfig::default()
        };
        assert!(endpoint_allowed(&config, "/dev/ttyUSB0"));
        assert!(!endpoint_allowed(&config, "/dev/ttyACM0"));
        assert!(endpoint_allowed(&config, "192.168.1.20:502"));
        assert!(!endpoint_allowed(&config, "10.0.0.1:502"));
        assert!(!endpoint_allowed(&ServeConfig::default(), "/dev/ttyUSB0"));
    }

    #[test]
    fn the_shipped_configuration_parses() {
        let text = include_str!("../../deploy/serve.toml");
        let config: ServeConfig =
            crate::config::kind_config::parse_strict(text, Path::new("deploy/serve.toml")).unwrap();
        assert!(config.listen.ip().is_loopback());
        assert!(endpoint_allowed(&config, "/dev/ttyUSB3"));
        assert!(config.devices.hold);
        assert_eq!(
            config.devices.release_idle_after().unwrap(),
            Some(std::time::Duration::from_secs(3600))
        );
    }

    #[test]
    fn a_bad_idle_time_names_the_key_and_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("serve.toml");
        for bad in ["-1.0", "0.0", "nan"] {
            std::fs::write(&path, format!("[devices]\nrelease_idle_after_s = {bad}\n")).unwrap();
            let err = format!("{:#}", ServeConfig::load(&path).unwrap_err());
            assert!(
                err.contains("devices.release_idle_after_s") && err.contains("serve.toml"),
                "{err}"
            );
        }
    }

    #[test]
    fn unknown_keys_name_the_key() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("serve.toml");
        std::fs::write(&path, "listen = \"127.0.0.1:1\"\nlisten_port = 3\n").unwrap();
        let err = ServeConfig::load(&path).unwrap_err().to_string();
        assert!(err.contains("listen_port"), "{err}");
    }
}
