//! Reading HAL pins of the running LinuxCNC at full precision: one long-lived Python process
//! with LinuxCNC's own `hal` module (a HAL user component), one line of values per request.
//! `halcmd getp` prints floats with 7 significant digits (0.1 µm at 1 m in mm), too coarse
//! for a trim of a few µm; `hal.get_value` returns the double (about 20 µs for three pins).

use std::io::{BufRead, BufReader, Write};
use std::path::Path;
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};

/// The interpreter with LinuxCNC's `hal` module (Debian's python3-linuxcnc files are built
/// for the system Python, not for another `python3` on PATH).
pub const SYSTEM_PYTHON: &str = "/usr/bin/python3";

/// Answers each input line with the pins' values (`repr`, round-trip exact) or `error ...`;
/// leaves HAL (its component removed) at end of input.
const READER_SCRIPT: &str = r#"
import os, sys, hal
pins = sys.argv[1:]
comp = hal.component("geocal-reader-%d" % os.getpid())
comp.ready()
try:
    for _ in sys.stdin:
        try:
            print(" ".join(repr(float(hal.get_value(p))) for p in pins), flush=True)
        except Exception as e:
            print("error " + str(e).replace("\n", " "), flush=True)
finally:
    comp.exit()
"#;

/// A reader of a fixed list of HAL pins.
pub struct HalReader {
    pins: Vec<String>,
    child: Child,
    stdin: Option<ChildStdin>,
    stdout: BufReader<ChildStdout>,
}

impl HalReader {
    /// Start the reader with LinuxCNC's environment (`RTAPI_UID`, `RTAPI_FIFO_PATH`, `HOME`).
    pub fn spawn(pins: Vec<String>, env: &[(String, String)], dir: &Path) -> std::io::Result<Self> {
        let mut cmd = Command::new(SYSTEM_PYTHON);
        cmd.arg("-c")
            .arg(READER_SCRIPT)
            .args(&pins)
            .current_dir(dir)
            .env_remove("DISPLAY")
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::null());
        for (k, v) in env {
            cmd.env(k, v);
        }
        let mut child = cmd.spawn()?;
        let (Some(stdin), Some(stdout)) = (child.stdin.take(), child.stdout.take()) else {
            let _ = child.kill();
            let _ = child.wait();
            return Err(std::io::Error::other("the HAL reader has no pipes"));
        };
        Ok(Self {
            pins,
            child,
            stdin: Some(stdin),
            stdout: BufReader::new(stdout),
        })
    }

    pub fn pins(&self) -> &[String] {
        &self.pins
    }

    /// The current value of every pin, in order.
    pub fn read(&mut self) -> std::io::Result<Vec<f64>> {
        let stdin = self
            .stdin
            .as_mut()
            .ok_or_else(|| std::io::Error::other("the HAL reader is closed"))?;
        stdin.write_all(b"\n")?;
        stdin.flush()?;
        let mut line = String::new();
        if self.stdout.read_line(&mut line)? == 0 {
            return Err(std::io::Error::new(
                std::io::ErrorKind::UnexpectedEof,
                "the HAL reader ended (LinuxCNC's HAL is gone, or the Python `hal` module is missing)",
            ));
        }
        parse_values(line.trim_end(), &self.pins)
    }

    /// End the reader: its HAL component leaves before LinuxCNC unloads HAL.
    pub fn close(&mut self) {
        self.stdin = None;
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
        while std::time::Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(10));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for HalReader {
    fn drop(&mut self) {
        self.close();
    }
}

fn parse_values(line: &str, pins: &[String]) -> std::io::Result<Vec<f64>> {
    if let Some(message) = line.strip_prefix("error ") {
        return Err(std::io::Error::other(format!(
            "reading HAL pins: {message}"
        )));
    }
    let values = line
        .split_whitespace()
        .map(str::parse::<f64>)
        .collect::<Result<Vec<f64>, _>>()
        .map_err(|e| {
            std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                format!("the HAL reader answered {line:?}: {e}"),
            )
        })?;
    if values.len() != pins.len() {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!(
                "the HAL reader answered {} values for {} pins: {line:?}",
                values.len(),
                pins.len()
            ),
        ));
    }
    Ok(values)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_and_errors_are_parsed() {
        let pins = vec!["a".to_string(), "b".to_string()];
        assert_eq!(
            parse_values("987.6543219000001 1.3e-06", &pins).unwrap(),
            vec![987.6543219000001, 1.3e-6]
        );
        assert!(parse_values("1.0", &pins).is_err());
        assert!(parse_values("1.0 x", &pins).is_err());
        let e = parse_values("error pin nope not found", &pins).unwrap_err();
        assert!(e.to_string().contains("nope"));
    }
}
