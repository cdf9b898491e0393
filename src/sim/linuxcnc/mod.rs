//! A real LinuxCNC (Debian's `linuxcnc-uspace`, simulation mode) started headless for a
//! real-controller HIL run or a test, from the facts in docs/linuxcnc.md:
//! - one instance on the machine at a time: a global file lock
//!   ([`LOCK_PATH`], `flock` exclusive) held for the instance's whole life;
//! - a private network namespace (`unshare -n`, loopback up), so that its listeners on
//!   0.0.0.0:5005/5007 never reach the machine's interfaces; geocal connects from a thread
//!   that joined the namespace ([`LinuxCnc::connect`]);
//! - `RTAPI_UID` = nobody, `RTAPI_FIFO_PATH` in a directory owned by it, a scratch `HOME`,
//!   no `DISPLAY`, `[DISPLAY] DISPLAY = linuxcncrsh`, `linuxcnc -r`;
//! - the log is watched and a start that fails ("can't initialize motion", e.g. a missing
//!   `COMP_FILE`) is reported with its tail;
//! - a watchdog process, holding the lock too, kills whatever is left in the namespace and
//!   removes LinuxCNC's shared memory and its lock file when geocal is done with it or dies.

pub mod hal;
pub mod host;
pub mod ini;

use std::fs::File;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::os::fd::AsRawFd;
use std::os::unix::fs::PermissionsExt;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};

pub use hal::HalReader;
pub use ini::{CompFile, MachineSetup};

/// Serialises every LinuxCNC instance geocal (or a developer by hand, `flock
/// /tmp/geocal-linuxcnc.lock ...`) starts on this machine.
pub const LOCK_PATH: &str = "/tmp/geocal-linuxcnc.lock";
/// linuxcncrsh's port inside the namespace.
pub const RSH_PORT: u16 = 5007;
/// linuxcncrsh's default connect and enable passwords (`linuxcncrsh(1)`).
pub const HELLO_PASSWORD: &str = "EMC";
pub const ENABLE_PASSWORD: &str = "EMCTOO";

/// Lines of LinuxCNC's log after which it never comes up.
const FATAL_LOG_LINES: [&str; 5] = [
    "can't initialize motion",
    "can't open compensation file",
    "Refusing to run as root",
    "insmod for",
    "Realtime system did not load",
];

/// System V IPC keys of LinuxCNC (NML buffers 1001-1005, HAL, RTAPI): removed after an
/// instance that did not shut down by itself.
const IPC_KEYS: [&str; 8] = [
    "0x000003e9",
    "0x000003ea",
    "0x000003eb",
    "0x000003ec",
    "0x000003ed",
    "0x48414c32",
    "0x48484c34",
    "0x00000064",
];

/// Runs beside geocal with the lock inherited (fd 3). When its stdin closes (geocal is done,
/// or died), it kills what is left in the namespace, removes LinuxCNC's IPC and lock file,
/// and exits, releasing the lock last.
const WATCHDOG_SCRIPT: &str = r#"
trap '' HUP INT TERM PIPE
read -r _ || true
ns="$1"
shift
round=0
while [ $round -lt 25 ]; do
  found=
  for p in /proc/[0-9]*; do
    if [ "$(readlink "$p/ns/net" 2>/dev/null)" = "$ns" ]; then
      found=1
      kill -9 "${p#/proc/}" 2>/dev/null
    fi
  done
  [ -z "$found" ] && break
  round=$((round + 1))
  sleep 0.2
done
for key in "$@"; do
  ipcrm -M "$key" 2>/dev/null
  ipcrm -S "$key" 2>/dev/null
done
rm -f /tmp/linuxcnc.lock
exit 0
"#;

/// Why LinuxCNC cannot run here, or None when it can: the programs a start needs.
pub fn unavailable() -> Option<String> {
    for program in ["linuxcnc", "unshare", "ip", "ipcrm"] {
        if find_in_path(program).is_none() {
            return Some(format!(
                "`{program}` is not on PATH (LinuxCNC: apt-get install linuxcnc-uspace)"
            ));
        }
    }
    if !Path::new(hal::SYSTEM_PYTHON).exists() {
        return Some(format!("{} is missing", hal::SYSTEM_PYTHON));
    }
    if unsafe { libc::geteuid() } != 0 {
        return Some("a private network namespace needs root (unshare -n)".into());
    }
    None
}

fn find_in_path(program: &str) -> Option<PathBuf> {
    std::env::var_os("PATH")?
        .to_str()?
        .split(':')
        .map(|d| Path::new(d).join(program))
        .find(|p| p.is_file())
}

/// A running LinuxCNC. Dropping it stops it (forcibly if [`LinuxCnc::shutdown`] was not
/// called) and leaves no process, shared memory or lock behind.
pub struct LinuxCnc {
    dir: tempfile::TempDir,
    env: Vec<(String, String)>,
    /// `unshare -n` → `sh` → the `linuxcnc` script (one pid throughout: each execs the next).
    script: Option<Child>,
    /// The namespace, held open for connecting after the script's pid is gone.
    netns: File,
    netns_id: String,
    watchdog: Option<Child>,
    /// Released after the watchdog, which holds it too, finished.
    lock: Option<File>,
}

impl LinuxCnc {
    /// Start LinuxCNC for `setup`, waiting up to `timeout` for linuxcncrsh to accept a
    /// connection. Blocks while another instance holds the lock.
    pub fn start(setup: &MachineSetup, timeout: Duration) -> anyhow::Result<Self> {
        if let Some(why) = unavailable() {
            bail!("LinuxCNC cannot run here: {why}");
        }
        for c in &setup.comp_files {
            if !c.file.is_file() {
                bail!(
                    "joint {}: compensation file {} does not exist (LinuxCNC would not start)",
                    c.joint,
                    c.file.display()
                );
            }
        }
        Self::launch(timeout, |dir| {
            let ini_path = dir.join("geocal.ini");
            std::fs::write(&ini_path, ini::ini_text(setup))?;
            std::fs::write(dir.join(ini::HAL_FILE), ini::hal_text())?;
            std::fs::write(dir.join("geocal.tbl"), "")?;
            std::fs::write(dir.join("geocal.var"), "")?;
            Ok(ini_path)
        })
    }

    /// Start LinuxCNC from someone else's configuration, e.g. one of the sample configs Debian
    /// ships: the files of `ini`'s directory are copied (symbolic links followed) into the
    /// scratch directory with only `[DISPLAY] DISPLAY` changed to `linuxcncrsh` and a shorter
    /// `[EMCMOT] COMM_TIMEOUT` raised to [`ini::COMM_TIMEOUT_S`] (`as_started_here`).
    pub fn start_config(ini: &Path, timeout: Duration) -> anyhow::Result<Self> {
        if let Some(why) = unavailable() {
            bail!("LinuxCNC cannot run here: {why}");
        }
        let source = ini
            .parent()
            .with_context(|| format!("{} has no directory", ini.display()))?;
        let name = ini
            .file_name()
            .with_context(|| format!("{} names no file", ini.display()))?;
        let text = std::fs::read_to_string(ini)
            .with_context(|| format!("reading LinuxCNC configuration {}", ini.display()))?;
        let text = as_started_here(&text)
            .with_context(|| format!("{}: no [DISPLAY] DISPLAY line", ini.display()))?;
        Self::launch(timeout, |dir| {
            let config = dir.join("config");
            std::fs::create_dir(&config)?;
            for entry in std::fs::read_dir(source)? {
                let path = entry?.path();
                if path.is_file() {
                    if let Some(file) = path.file_name() {
                        std::fs::copy(&path, config.join(file))?;
                    }
                }
            }
            let ini_path = config.join(name);
            std::fs::write(&ini_path, &text)?;
            Ok(ini_path)
        })
    }

    /// Take the lock, make the scratch directory, let `write_config` put the configuration
    /// into it (returning its INI's path), start LinuxCNC and wait for linuxcncrsh.
    fn launch(
        timeout: Duration,
        write_config: impl FnOnce(&Path) -> std::io::Result<PathBuf>,
    ) -> anyhow::Result<Self> {
        let lock = take_lock()?;
        if let Some(pid) = running_linuxcnc() {
            bail!(
                "a LinuxCNC not started by geocal is running (pid {pid}); its script would stop \
                 it, so geocal does not start another"
            );
        }
        // A crashed instance's lock file would make the script look for it.
        let _ = std::fs::remove_file("/tmp/linuxcnc.lock");

        let dir = tempfile::Builder::new()
            .prefix("geocal-linuxcnc-")
            .tempdir()
            .context("creating LinuxCNC's directory")?;
        let uid = nobody_uid();
        let fifo_dir = dir.path().join("rtapi");
        let home = dir.path().join("home");
        std::fs::create_dir(&fifo_dir)?;
        std::fs::create_dir(&home)?;
        // nobody must traverse the directory to its fifo's.
        std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755))?;
        std::fs::set_permissions(&fifo_dir, std::fs::Permissions::from_mode(0o700))?;
        std::os::unix::fs::chown(&fifo_dir, Some(uid), None)
            .context("handing the RTAPI fifo directory to nobody")?;
        let ini_path = write_config(dir.path()).context("writing LinuxCNC's configuration")?;
        let env = vec![
            ("RTAPI_UID".to_string(), uid.to_string()),
            (
                "RTAPI_FIFO_PATH".to_string(),
                fifo_dir.join("rtapi_fifo").display().to_string(),
            ),
            ("HOME".to_string(), home.display().to_string()),
        ];
        let log = File::create(dir.path().join("linuxcnc.log"))?;
        let mut cmd = Command::new("unshare");
        cmd.args(["-n", "--", "sh", "-c"])
            .arg("ip link set lo up && exec linuxcnc -r \"$0\"")
            .arg(&ini_path)
            .current_dir(ini_path.parent().unwrap_or(dir.path()))
            .env_remove("DISPLAY")
            .stdin(Stdio::null())
            .stdout(log.try_clone()?)
            .stderr(log)
            .process_group(0);
        for (k, v) in &env {
            cmd.env(k, v);
        }
        let mut script = cmd.spawn().context("starting `unshare -n ... linuxcnc`")?;
        let (netns, netns_id) = match wait_for_namespace(script.id()) {
            Ok(ns) => ns,
            Err(e) => {
                let _ = script.kill();
                let _ = script.wait();
                return Err(e);
            }
        };
        let watchdog = spawn_watchdog(&lock, &netns_id);
        let mut me = LinuxCnc {
            dir,
            env,
            script: Some(script),
            netns,
            netns_id,
            watchdog: None,
            lock: Some(lock),
        };
        me.watchdog = Some(watchdog.context("starting the LinuxCNC watchdog")?);
        me.wait_ready(timeout)?;
        Ok(me)
    }

    fn log_path(&self) -> PathBuf {
        self.dir.path().join("linuxcnc.log")
    }

    /// The last `lines` lines of LinuxCNC's output.
    pub fn log_tail(&self, lines: usize) -> String {
        let text = std::fs::read_to_string(self.log_path()).unwrap_or_default();
        let all: Vec<&str> = text.lines().collect();
        all[all.len().saturating_sub(lines)..].join("\n")
    }

    fn wait_ready(&mut self, timeout: Duration) -> anyhow::Result<()> {
        let deadline = Instant::now() + timeout;
        loop {
            let log = std::fs::read_to_string(self.log_path()).unwrap_or_default();
            if let Some(line) = FATAL_LOG_LINES.iter().find(|l| log.contains(*l)) {
                bail!(
                    "LinuxCNC did not start ({line:?} in its log); its log ends:\n{}",
                    self.log_tail(15)
                );
            }
            if let Some(script) = self.script.as_mut() {
                if let Ok(Some(status)) = script.try_wait() {
                    bail!(
                        "LinuxCNC ended while starting ({status}); its log ends:\n{}",
                        self.log_tail(15)
                    );
                }
            }
            if self.connect().is_ok() {
                return Ok(());
            }
            if Instant::now() > deadline {
                bail!(
                    "linuxcncrsh did not accept a connection within {:.0} s; LinuxCNC's log ends:\n{}",
                    timeout.as_secs_f64(),
                    self.log_tail(15)
                );
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// The scratch directory holding the INI, HAL file and log.
    pub fn dir(&self) -> &Path {
        self.dir.path()
    }

    /// `RTAPI_UID`, `RTAPI_FIFO_PATH`, `HOME`: what a HAL client of this instance needs.
    pub fn env(&self) -> &[(String, String)] {
        &self.env
    }

    /// A TCP connection to linuxcncrsh inside the instance's namespace.
    pub fn connect(&self) -> std::io::Result<TcpStream> {
        connect_in(&self.netns, RSH_PORT)
    }

    /// A connector that can outlive `self`'s borrow (the namespace file is duplicated).
    pub fn connector(&self) -> std::io::Result<Connector> {
        Ok(Connector {
            netns: std::sync::Arc::new(self.netns.try_clone()?),
        })
    }

    /// A reader of HAL pins of this instance; drop it before [`LinuxCnc::shutdown`].
    pub fn hal_reader(&self, pins: Vec<String>) -> std::io::Result<HalReader> {
        HalReader::spawn(pins, &self.env, self.dir.path())
    }

    /// Stop LinuxCNC as its user would (`shutdown` over linuxcncrsh), wait for its script,
    /// then let the watchdog sweep and check that nothing is left.
    pub fn shutdown(mut self) -> anyhow::Result<()> {
        let asked = self.ask_shutdown();
        let ended = self.wait_script(Duration::from_secs(60));
        let swept = self.sweep();
        asked.context("asking LinuxCNC to shut down")?;
        if !ended {
            bail!(
                "LinuxCNC did not end within 60 s of `shutdown` (killed); its log ends:\n{}",
                self.log_tail(10)
            );
        }
        swept
    }

    fn ask_shutdown(&self) -> std::io::Result<()> {
        let mut s = self.connect()?;
        s.set_read_timeout(Some(Duration::from_secs(10)))?;
        s.write_all(
            format!(
                "hello {HELLO_PASSWORD} geocal 1.0\r\nset enable {ENABLE_PASSWORD}\r\nshutdown\r\n"
            )
            .as_bytes(),
        )?;
        // Until LinuxCNC closes the connection (or the timeout).
        let mut sink = Vec::new();
        let _ = s.read_to_end(&mut sink);
        Ok(())
    }

    /// Wait for the `linuxcnc` script; true if it ended by itself.
    fn wait_script(&mut self, timeout: Duration) -> bool {
        let Some(script) = self.script.as_mut() else {
            return true;
        };
        let deadline = Instant::now() + timeout;
        while Instant::now() < deadline {
            if let Ok(Some(_)) = script.try_wait() {
                self.script = None;
                return true;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = script.kill();
        let _ = script.wait();
        self.script = None;
        false
    }

    /// Close the watchdog's stdin and wait for its sweep, then release the lock; check that
    /// no process is left in the namespace and no LinuxCNC shared memory remains.
    fn sweep(&mut self) -> anyhow::Result<()> {
        if let Some(script) = self.script.as_mut() {
            // Forced: the watchdog kills the rest of the namespace.
            let _ = script.kill();
            let _ = script.wait();
            self.script = None;
        }
        if let Some(mut watchdog) = self.watchdog.take() {
            drop(watchdog.stdin.take());
            let deadline = Instant::now() + Duration::from_secs(30);
            loop {
                match watchdog.try_wait() {
                    Ok(Some(_)) => break,
                    Ok(None) if Instant::now() < deadline => {
                        std::thread::sleep(Duration::from_millis(20))
                    }
                    _ => {
                        let _ = watchdog.kill();
                        let _ = watchdog.wait();
                        break;
                    }
                }
            }
        }
        let left = processes_in_namespace(&self.netns_id);
        let shm = linuxcnc_shared_memory();
        self.lock = None;
        if !left.is_empty() {
            bail!("processes left in LinuxCNC's namespace: {left:?}");
        }
        if !shm.is_empty() {
            bail!("LinuxCNC shared memory left: {shm:?}");
        }
        Ok(())
    }
}

impl Drop for LinuxCnc {
    fn drop(&mut self) {
        if self.lock.is_some() {
            if let Err(e) = self.sweep() {
                tracing::warn!("stopping LinuxCNC: {e:#}");
            }
        }
    }
}

/// `text` (an INI file) as it starts on this computer: its `[DISPLAY]` section's `DISPLAY`
/// set to `linuxcncrsh`, and an `[EMCMOT] COMM_TIMEOUT` below [`ini::COMM_TIMEOUT_S`] raised
/// to it (without a realtime kernel a loaded computer stalls the servo thread past LinuxCNC's
/// own 1.0 s, and the task drops the command); None without a `DISPLAY` line.
fn as_started_here(text: &str) -> Option<String> {
    let mut section = "";
    let mut changed = false;
    let mut out = String::with_capacity(text.len());
    for line in text.lines() {
        let t = line.trim();
        if t.starts_with('[') {
            section = t;
        }
        let value_of = |key: &str| {
            t.split_once('=')
                .filter(|(k, _)| k.trim() == key)
                .map(|(_, v)| v.trim())
        };
        let is_display = section == "[DISPLAY]" && value_of("DISPLAY").is_some();
        let short_wait = section == "[EMCMOT]"
            && value_of("COMM_TIMEOUT")
                .and_then(|v| v.parse::<f64>().ok())
                .is_some_and(|s| s < ini::COMM_TIMEOUT_S);
        if is_display && !changed {
            out.push_str("DISPLAY = linuxcncrsh");
            changed = true;
        } else if short_wait {
            out.push_str(&format!("COMM_TIMEOUT = {:.1}", ini::COMM_TIMEOUT_S));
        } else {
            out.push_str(line);
        }
        out.push('\n');
    }
    changed.then_some(out)
}

/// Opens linuxcncrsh connections inside a LinuxCNC's namespace (cheap to clone).
#[derive(Clone)]
pub struct Connector {
    netns: std::sync::Arc<File>,
}

impl Connector {
    pub fn connect(&self) -> std::io::Result<TcpStream> {
        connect_in(&self.netns, RSH_PORT)
    }

    /// Start `work` on a thread of its own inside the namespace, as a program started there
    /// would run (`nsenter --net=...`): every socket it opens, on that thread or on threads
    /// it starts, reaches this LinuxCNC at 127.0.0.1. Joining gives its result, or the error
    /// of entering the namespace.
    pub fn spawn_inside<T: Send + 'static>(
        &self,
        work: impl FnOnce() -> T + Send + 'static,
    ) -> std::io::Result<std::thread::JoinHandle<std::io::Result<T>>> {
        let ns = self.netns.try_clone()?;
        Ok(std::thread::spawn(move || {
            // SAFETY: setns on this thread only; the fd is a namespace file `ns` keeps open.
            if unsafe { libc::setns(ns.as_raw_fd(), libc::CLONE_NEWNET) } != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(work())
        }))
    }

    /// The same, as a tokio stream (the blocking connect runs on a blocking thread).
    pub async fn connect_tokio(&self) -> std::io::Result<tokio::net::TcpStream> {
        let me = self.clone();
        let std_stream = tokio::task::spawn_blocking(move || me.connect())
            .await
            .map_err(std::io::Error::other)??;
        std_stream.set_nonblocking(true)?;
        tokio::net::TcpStream::from_std(std_stream)
    }
}

/// Connect to 127.0.0.1:`port` of the namespace `netns` from a thread that joins it (a socket
/// belongs to the namespace it was created in, whichever thread uses it later).
fn connect_in(netns: &File, port: u16) -> std::io::Result<TcpStream> {
    let ns = netns.try_clone()?;
    std::thread::spawn(move || {
        // SAFETY: setns on this thread only (CLONE_NEWNET affects the calling thread);
        // the fd is a namespace file that `ns` keeps open.
        if unsafe { libc::setns(ns.as_raw_fd(), libc::CLONE_NEWNET) } != 0 {
            return Err(std::io::Error::last_os_error());
        }
        let address = std::net::SocketAddr::from(([127, 0, 0, 1], port));
        TcpStream::connect_timeout(&address, Duration::from_secs(5))
    })
    .join()
    .map_err(|_| std::io::Error::other("the namespace thread panicked"))?
}

fn take_lock() -> anyhow::Result<File> {
    let lock = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(LOCK_PATH)
        .with_context(|| format!("opening {LOCK_PATH}"))?;
    // SAFETY: flock on an fd we own.
    if unsafe { libc::flock(lock.as_raw_fd(), libc::LOCK_EX) } != 0 {
        return Err(std::io::Error::last_os_error()).context(format!("locking {LOCK_PATH}"));
    }
    Ok(lock)
}

fn nobody_uid() -> u32 {
    // SAFETY: getpwnam with a NUL-terminated name; the result is read at once.
    let pw = unsafe { libc::getpwnam(c"nobody".as_ptr()) };
    if pw.is_null() {
        65534
    } else {
        unsafe { (*pw).pw_uid }
    }
}

fn ns_link(pid: &str) -> Option<String> {
    std::fs::read_link(format!("/proc/{pid}/ns/net"))
        .ok()
        .map(|p| p.display().to_string())
}

/// Wait until `unshare` entered its new namespace; open it.
fn wait_for_namespace(pid: u32) -> anyhow::Result<(File, String)> {
    let own = ns_link("self").context("reading this process's network namespace")?;
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        match ns_link(&pid.to_string()) {
            Some(ns) if ns != own => {
                let file = File::open(format!("/proc/{pid}/ns/net"))
                    .context("opening LinuxCNC's network namespace")?;
                // The process may have moved on between the two reads; check it is the same.
                if ns_link(&pid.to_string()).as_deref() == Some(ns.as_str()) {
                    return Ok((file, ns));
                }
            }
            Some(_) if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(5)),
            _ => bail!("`unshare -n` did not enter a new network namespace"),
        }
    }
}

fn spawn_watchdog(lock: &File, netns_id: &str) -> std::io::Result<Child> {
    let lock_fd = lock.as_raw_fd();
    let mut cmd = Command::new("sh");
    cmd.arg("-c")
        .arg(WATCHDOG_SCRIPT)
        .arg("geocal-linuxcnc-watchdog")
        .arg(netns_id)
        .args(IPC_KEYS)
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .process_group(0);
    // SAFETY: only fcntl, async-signal-safe, between fork and exec: the child keeps the
    // lock's open file description (and with it the lock) across exec.
    unsafe {
        cmd.pre_exec(move || {
            if libc::fcntl(lock_fd, libc::F_SETFD, 0) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    cmd.spawn()
}

/// Pids of the processes in network namespace `netns_id` (`net:[inode]`).
fn processes_in_namespace(netns_id: &str) -> Vec<u32> {
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    entries
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .filter(|pid| ns_link(&pid.to_string()).as_deref() == Some(netns_id))
        .collect()
}

/// A live process of LinuxCNC's realtime or server, wherever it runs (zombies of a stopped
/// instance linger for a second or two and do not count).
fn running_linuxcnc() -> Option<u32> {
    let entries = std::fs::read_dir("/proc").ok()?;
    entries
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .find(|pid| {
            let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
                return false;
            };
            // "pid (comm) state ...": comm may hold spaces, the state follows the last ')'.
            let (Some(open), Some(close)) = (stat.find('('), stat.rfind(')')) else {
                return false;
            };
            let comm = &stat[open + 1..close];
            let zombie = stat[close + 1..].trim_start().starts_with(['Z', 'X']);
            !zombie
                && matches!(
                    comm,
                    "rtapi_app" | "linuxcncsvr" | "milltask" | "linuxcncrsh"
                )
        })
}

/// LinuxCNC's System V shared memory segments that exist (by key).
pub fn linuxcnc_shared_memory() -> Vec<String> {
    let Ok(text) = std::fs::read_to_string("/proc/sysvipc/shm") else {
        return Vec::new();
    };
    text.lines()
        .skip(1)
        .filter_map(|l| l.split_whitespace().next()?.parse::<i64>().ok())
        .map(|key| format!("0x{:08x}", key as u32))
        .filter(|key| IPC_KEYS.contains(&key.as_str()))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::as_started_here;

    #[test]
    fn only_the_display_line_and_a_short_motion_wait_change() {
        let ini = "[EMC]\nDISPLAY = x\nCOMM_TIMEOUT = 1.0\n[DISPLAY]\n# DISPLAY = tklinuxcnc\nDISPLAY = axis\nCYCLE_TIME = 0.1\n[EMCMOT]\nCOMM_TIMEOUT = 1.0\nSERVO_PERIOD = 1000000\n";
        assert_eq!(
            as_started_here(ini).as_deref(),
            Some("[EMC]\nDISPLAY = x\nCOMM_TIMEOUT = 1.0\n[DISPLAY]\n# DISPLAY = tklinuxcnc\nDISPLAY = linuxcncrsh\nCYCLE_TIME = 0.1\n[EMCMOT]\nCOMM_TIMEOUT = 5.0\nSERVO_PERIOD = 1000000\n")
        );
        let longer = "[DISPLAY]\nDISPLAY = axis\n[EMCMOT]\nCOMM_TIMEOUT = 8\n";
        assert_eq!(
            as_started_here(longer).as_deref(),
            Some("[DISPLAY]\nDISPLAY = linuxcncrsh\n[EMCMOT]\nCOMM_TIMEOUT = 8\n")
        );
        assert_eq!(as_started_here("[EMC]\nDISPLAY = axis\n"), None);
    }
}
