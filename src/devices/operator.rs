//! The operator of a real run at a console: prints what to do (place the tracer on a station,
//! mount a reflector), waits for Enter, and keeps each prompt with its acknowledgement time.

pub use crate::config::operator::OperatorConfig;
use std::io::{BufRead, IsTerminal, Write};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use async_trait::async_trait;
use geocal_drivers::{DeviceError, Operator};
use serde::Serialize;
use tokio::sync::mpsc;

/// One prompt and when it was acknowledged (Unix seconds).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Prompt {
    pub instruction: String,
    pub prompted_unix_s: f64,
    pub acknowledged_unix_s: f64,
}

fn unix_s() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// Prompts on `output`, acknowledgements as lines of `input` (read on a thread of its own,
/// so that waiting for the operator never stalls the drivers' tasks).
pub struct ConsoleOperator {
    lines: mpsc::UnboundedReceiver<std::io::Result<String>>,
    output: Box<dyn Write + Send>,
    /// Every prompt so far, in order.
    pub log: Vec<Prompt>,
}

impl ConsoleOperator {
    pub fn new(input: impl BufRead + Send + 'static, output: Box<dyn Write + Send>) -> Self {
        let (tx, lines) = mpsc::unbounded_channel();
        std::thread::spawn(move || {
            for line in input.lines() {
                let stop = line.is_err();
                if tx.send(line).is_err() || stop {
                    break;
                }
            }
        });
        Self {
            lines,
            output,
            log: Vec::new(),
        }
    }

    /// The operator at this process's console: prompts on stderr, Enter on stdin. Stdin
    /// must be a terminal unless `config.piped_stdin` (a clear error otherwise, rather than
    /// a run that takes end-of-file or a stray line for "done").
    pub fn stdin(config: &OperatorConfig) -> anyhow::Result<Self> {
        let stdin = std::io::stdin();
        if !stdin.is_terminal() && !config.piped_stdin {
            anyhow::bail!(
                "a real run asks the operator to place the tracer and mount reflectors, and waits \
                 for Enter on stdin, but stdin is not a terminal; run geocal from a terminal, or \
                 pass --yes (or set [operator] piped_stdin = true) to read each acknowledgement \
                 as a line from stdin"
            );
        }
        Ok(Self::new(
            std::io::BufReader::new(stdin),
            Box::new(std::io::stderr()),
        ))
    }

    async fn ask(&mut self, instruction: String) -> Result<(), DeviceError> {
        let operator = |message: String| DeviceError::Disconnected {
            device: "operator".into(),
            message,
        };
        let prompted_unix_s = unix_s();
        let started = Instant::now();
        let shown = writeln!(self.output, "[operator] {instruction}, then press Enter")
            .and_then(|()| self.output.flush());
        shown.map_err(|e| operator(format!("cannot show the prompt: {e}")))?;
        tracing::info!(instruction, "operator prompt");
        match self.lines.recv().await {
            Some(Ok(_)) => {}
            Some(Err(e)) => return Err(operator(format!("reading stdin: {e}"))),
            None => {
                return Err(operator(format!(
                    "stdin closed before the operator acknowledged: {instruction}"
                )))
            }
        }
        let waited_s = started.elapsed().as_secs_f64();
        let _ = writeln!(self.output, "[operator] acknowledged after {waited_s:.2} s");
        let _ = self.output.flush();
        tracing::info!(instruction, waited_s, "operator acknowledged");
        self.log.push(Prompt {
            instruction,
            prompted_unix_s,
            acknowledged_unix_s: unix_s(),
        });
        Ok(())
    }
}

fn metres(v: [f64; 3]) -> String {
    format!("({:.4}, {:.4}, {:.4}) m", v[0], v[1], v[2])
}

/// What the operator is asked to do to place the tracer on a station.
pub fn place_station_instruction(index: usize, id: &str, hint_m: Option<[f64; 3]>) -> String {
    let near = hint_m.map_or(String::new(), |h| format!(" near {}", metres(h)));
    format!(
        "place the tracer on station {id} (station {} of the plan){near}",
        index + 1
    )
}

/// What the operator is asked to do to mount a reflector.
pub fn mount_target_instruction(target: &str, offset_m: [f64; 3]) -> String {
    format!(
        "mount reflector {target} at offset {} from the tool point",
        metres(offset_m)
    )
}

#[async_trait]
impl Operator for ConsoleOperator {
    async fn place_station(
        &mut self,
        index: usize,
        id: &str,
        hint_m: Option<[f64; 3]>,
    ) -> Result<(), DeviceError> {
        self.ask(place_station_instruction(index, id, hint_m)).await
    }

    async fn mount_target(&mut self, target: &str, offset_m: [f64; 3]) -> Result<(), DeviceError> {
        self.ask(mount_target_instruction(target, offset_m)).await
    }
}

/// A simulated or emulated run that asks its operator first, as a real run would, then lets
/// the simulated operator act (`[operator] rehearse = true`).
pub struct Rehearsal {
    pub ask: Box<dyn Operator>,
    pub act: Box<dyn Operator>,
}

#[async_trait]
impl Operator for Rehearsal {
    async fn place_station(
        &mut self,
        index: usize,
        id: &str,
        hint_m: Option<[f64; 3]>,
    ) -> Result<(), DeviceError> {
        self.ask.place_station(index, id, hint_m).await?;
        self.act.place_station(index, id, hint_m).await
    }

    async fn mount_target(&mut self, target: &str, offset_m: [f64; 3]) -> Result<(), DeviceError> {
        self.ask.mount_target(target, offset_m).await?;
        self.act.mount_target(target, offset_m).await
    }
}

#[cfg(test)]
mod tests {
    use std::sync::{Arc, Mutex};

    use super::*;

    /// Collects what the operator prints.
    #[derive(Clone, Default)]
    struct Screen(Arc<Mutex<Vec<u8>>>);

    impl Write for Screen {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            self.0.lock().map_or(Ok(0), |mut v| {
                v.extend_from_slice(buf);
                Ok(buf.len())
            })
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    impl Screen {
        fn text(&self) -> String {
            String::from_utf8_lossy(&self.0.lock().map(|v| v.clone()).unwrap_or_default())
                .into_owned()
        }
    }

    #[tokio::test]
    async fn prompts_wait_for_a_line_and_are_logged() {
        // A pipe: the acknowledgement arrives 50 ms after the prompt.
        let (reader, mut writer) = std::io::pipe().expect("pipe");
        let screen = Screen::default();
        let mut op =
            ConsoleOperator::new(std::io::BufReader::new(reader), Box::new(screen.clone()));
        let feeder = std::thread::spawn(move || {
            std::thread::sleep(std::time::Duration::from_millis(50));
            writer.write_all(b"\n").expect("enter");
            std::thread::sleep(std::time::Duration::from_millis(20));
            writer.write_all(b"done\n").expect("enter");
        });
        let t0 = Instant::now();
        op.place_station(4, "s5", Some([0.1, -0.25, 0.3]))
            .await
            .expect("ack");
        assert!(t0.elapsed().as_secs_f64() >= 0.045, "waited for Enter");
        op.mount_target("t1", [0.0, 0.05, -0.1]).await.expect("ack");
        feeder.join().expect("feeder");
        let text = screen.text();
        assert!(
            text.contains("place the tracer on station s5 (station 5 of the plan) near (0.1000, -0.2500, 0.3000) m, then press Enter"),
            "{text}"
        );
        assert!(
            text.contains("mount reflector t1 at offset (0.0000, 0.0500, -0.1000) m"),
            "{text}"
        );
        assert_eq!(op.log.len(), 2);
        let p = &op.log[0];
        assert!(p.acknowledged_unix_s - p.prompted_unix_s >= 0.045);
        // End of input: a clear error, not a silent "done".
        let err = op.place_station(5, "s6", None).await.expect_err("eof");
        assert!(err.to_string().contains("stdin closed"), "{err}");
    }
}
