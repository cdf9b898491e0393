//! A file whose messages are not in chunks (an unchunked writer's), cut into runs of whole
//! top-level records that the parallel read decodes as it decodes chunks, from the file, so
//! that such a file is not read whole into memory either.

use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};

use mcap::records::op;

use crate::session::damage::{le_u64, RECORD_PREFIX};

/// About the size of a chunk as geocal's recorder writes it (uncompressed); tests' small
/// files need small runs to have several.
const RUN_BYTES: u64 = if cfg!(test) { 4096 } else { 1 << 20 };
/// The scan reads only the records' prefixes, through a buffer of this size.
const SCAN_BUFFER: usize = 1 << 20;

/// The data section of `file` (`len` bytes) as runs of whole records, in file order; None
/// when a record runs past the end, the data section holds a chunk (the indexed read is
/// then the one that applies), or the file cannot be read.
pub(super) fn record_runs(file: &File, len: u64) -> Option<Vec<(usize, usize)>> {
    let start = mcap::MAGIC.len() as u64;
    let mut reader = BufReader::with_capacity(SCAN_BUFFER, file);
    reader.seek(SeekFrom::Start(start)).ok()?;
    let (mut pos, mut run_start) = (start, start);
    let mut runs = Vec::new();
    let mut push = |from: u64, to: u64| -> Option<()> {
        runs.push((usize::try_from(from).ok()?, usize::try_from(to).ok()?));
        Some(())
    };
    loop {
        let mut prefix = [0u8; RECORD_PREFIX];
        reader.read_exact(&mut prefix).ok()?;
        match prefix[0] {
            op::DATA_END | op::FOOTER => break,
            op::CHUNK => return None,
            _ => {}
        }
        let body = le_u64(&prefix[1..]);
        let end = (pos + RECORD_PREFIX as u64).checked_add(body)?;
        if end > len {
            return None;
        }
        reader.seek_relative(i64::try_from(body).ok()?).ok()?;
        pos = end;
        if pos - run_start >= RUN_BYTES {
            push(run_start, pos)?;
            run_start = pos;
        }
    }
    if pos > run_start {
        push(run_start, pos)?;
    }
    Some(runs)
}
