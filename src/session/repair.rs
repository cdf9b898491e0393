//! `geocal repair`: every readable message of a truncated or damaged session, copied in file
//! order into a complete MCAP file (summary, indexes, CRCs), and an account of what was lost.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;

use super::messages::{RunEvent, TOPIC_EVENT};
use super::reader::{read_raw, Completeness, DamagedChunk, RawMessage, RawRead, ReadError};
use super::recorder::{Recorder, RecorderError, RecorderOptions};

#[derive(Debug, Clone)]
pub struct RepairReport {
    pub input: PathBuf,
    pub output: PathBuf,
    /// Messages copied (every readable one).
    pub messages: u64,
    /// What the input lost: damaged chunks and where it was cut short.
    pub damaged: Vec<DamagedChunk>,
    pub completeness: Completeness,
    /// Whether the copy holds the `/geocal/session` header (solve needs it).
    pub has_header: bool,
}

#[derive(Debug, thiserror::Error)]
pub enum RepairError {
    #[error(transparent)]
    Read(#[from] ReadError),
    #[error("{0} is the input session; give another file with --out FILE")]
    SameFile(PathBuf),
    #[error(transparent)]
    Write(#[from] RecorderError),
    #[error("cannot move the repaired copy {from} to {to}: {source}")]
    Rename {
        from: PathBuf,
        to: PathBuf,
        source: std::io::Error,
    },
    #[error(
        "the repaired copy {file} does not read back as written ({why}); it was removed and \
         {input} is unchanged"
    )]
    Verify {
        file: PathBuf,
        input: PathBuf,
        why: String,
    },
}

/// The default output: `NAME.repaired.mcap` beside the input.
pub fn default_output(input: &Path) -> PathBuf {
    let stem = input
        .file_stem()
        .map_or_else(|| "session".into(), |s| s.to_string_lossy());
    input.with_file_name(format!("{stem}.repaired.mcap"))
}

/// Copies every readable message of `input` into a new, complete file at `output`. The copy is
/// written beside `output` first, read back, then moved into place: a failure leaves no
/// half-written `output`.
pub fn repair(input: &Path, output: &Path) -> Result<RepairReport, RepairError> {
    if same_file(input, output) {
        return Err(RepairError::SameFile(output.to_owned()));
    }
    let raw = read_raw(input)?;
    let partial = output.with_file_name(format!(
        ".{}.partial",
        output
            .file_name()
            .map_or_else(|| "repaired".into(), |n| n.to_string_lossy())
    ));
    let written = write_copy(&raw, &partial).and_then(|()| verify(&raw, &partial, input));
    if let Err(err) = written {
        let _ = std::fs::remove_file(&partial);
        return Err(err);
    }
    std::fs::rename(&partial, output).map_err(|source| RepairError::Rename {
        from: partial.clone(),
        to: output.to_owned(),
        source,
    })?;
    Ok(RepairReport {
        input: input.to_owned(),
        output: output.to_owned(),
        messages: raw.messages.len() as u64,
        has_header: raw
            .messages
            .iter()
            .any(|m| m.channel.topic == super::messages::TOPIC_SESSION),
        damaged: raw.damaged,
        completeness: raw.completeness,
    })
}

fn same_file(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    }
}

fn write_copy(raw: &RawRead, path: &Path) -> Result<(), RepairError> {
    // One chunk close at the end: nothing runs live here.
    let options = RecorderOptions {
        flush_interval: Duration::from_secs(24 * 3600),
        ..RecorderOptions::default()
    };
    let recorder = Recorder::create(path, options)?;
    let handle = recorder.handle();
    // The copy is complete, but what its original lost must still cost the windows it cost
    // there: each loss goes into the copy as an event, in log-time order.
    let mut losses: Vec<&DamagedChunk> = raw.damaged.iter().collect();
    losses.sort_by_key(|d| d.start_log_time_ns);
    let mut losses = losses.into_iter().peekable();
    let record_loss = |lost: &DamagedChunk| {
        handle.event(
            &RunEvent::DataLost { lost: lost.clone() },
            lost.start_log_time_ns,
        )
    };
    for message in &raw.messages {
        while let Some(lost) = losses.next_if(|d| d.start_log_time_ns < message.log_time_ns) {
            record_loss(lost);
        }
        handle.raw(message.clone());
    }
    losses.for_each(record_loss);
    recorder.finish()?;
    Ok(())
}

/// A `data_lost` event: what a repair records of its original's losses.
fn is_loss_record(message: &RawMessage) -> bool {
    message.channel.topic == TOPIC_EVENT
        && serde_json::from_slice::<RunEvent>(&message.data)
            .is_ok_and(|e| matches!(e, RunEvent::DataLost { .. }))
}

/// The copy must read complete and undamaged, with the same messages in the same order.
fn verify(raw: &RawRead, path: &Path, input: &Path) -> Result<(), RepairError> {
    let fail = |why: String| RepairError::Verify {
        file: path.to_owned(),
        input: input.to_owned(),
        why,
    };
    let back = read_raw(path)?;
    if !back.completeness.is_complete() || !back.damaged.is_empty() {
        return Err(fail("it is incomplete or damaged".into()));
    }
    let (back_losses, back_copied): (Vec<&RawMessage>, Vec<&RawMessage>) =
        back.messages.iter().partition(|m| is_loss_record(m));
    let (raw_losses, raw_copied): (Vec<&RawMessage>, Vec<&RawMessage>) =
        raw.messages.iter().partition(|m| is_loss_record(m));
    if back_copied.len() != raw_copied.len() {
        return Err(fail(format!(
            "{} messages instead of {}",
            back_copied.len(),
            raw_copied.len()
        )));
    }
    if back_losses.len() != raw_losses.len() + raw.damaged.len() {
        return Err(fail(format!(
            "{} records of lost data instead of {}",
            back_losses.len(),
            raw_losses.len() + raw.damaged.len()
        )));
    }
    let differs = back_copied.iter().zip(&raw_copied).position(|(a, b)| {
        (a.log_time_ns, a.publish_time_ns, &a.data, &a.channel.topic)
            != (b.log_time_ns, b.publish_time_ns, &b.data, &b.channel.topic)
    });
    match differs {
        Some(i) => Err(fail(format!("message {i} differs"))),
        None => Ok(()),
    }
}

/// What was kept and what was lost, for the terminal.
pub fn text(report: &RepairReport) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "{}: {} messages copied to {}",
        report.input.display(),
        report.messages,
        report.output.display()
    );
    if report.damaged.is_empty() && report.completeness.is_complete() {
        let _ = writeln!(s, "  nothing lost: the input was complete and undamaged");
    }
    for chunk in &report.damaged {
        let _ = writeln!(s, "  lost: damaged {}", chunk.describe());
        for (topic, n) in &chunk.lost_by_topic {
            let _ = writeln!(s, "    {n} on {topic}");
        }
    }
    if let Completeness::Truncated {
        bytes_read,
        file_bytes,
        reason,
        ..
    } = &report.completeness
    {
        let _ = if bytes_read < file_bytes {
            writeln!(
                s,
                "  lost: bytes {bytes_read}..{file_bytes}, the cut end of the file ({reason})"
            )
        } else {
            writeln!(
                s,
                "  the input ends without summary or footer ({reason}): rebuilt"
            )
        };
    }
    if !report.has_header {
        let _ = writeln!(
            s,
            "  the /geocal/session header was lost: `geocal solve` cannot read the copy"
        );
    }
    s
}
