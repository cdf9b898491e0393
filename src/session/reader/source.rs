//! Where a read takes its chunks' bytes from: a file read whole into memory (damaged, cut
//! short or foreign files, which the linear walk needs whole), or the file itself, one chunk
//! at a time, so that a complete file is never held whole.

use std::fs::File;
use std::os::unix::fs::FileExt;

#[derive(Clone, Copy)]
pub(super) enum Bytes<'a> {
    Memory(&'a [u8]),
    File { file: &'a File, len: u64 },
}

impl<'a> Bytes<'a> {
    pub(super) fn len(&self) -> u64 {
        match self {
            Bytes::Memory(buf) => buf.len() as u64,
            Bytes::File { len, .. } => *len,
        }
    }

    /// The bytes `start..end`, borrowed from memory or read into `scratch`.
    pub(super) fn range<'s>(
        &'s self,
        start: usize,
        end: usize,
        scratch: &'s mut Vec<u8>,
    ) -> std::io::Result<&'s [u8]> {
        match self {
            Bytes::Memory(buf) => Ok(&buf[start..end]),
            Bytes::File { file, .. } => {
                // Zeroed only where it grows: the read overwrites what it returns.
                let len = end - start;
                if scratch.len() < len {
                    scratch.resize(len, 0);
                }
                let bytes = &mut scratch[..len];
                file.read_exact_at(bytes, start as u64)?;
                Ok(bytes)
            }
        }
    }

    /// The whole buffer, when the bytes are in memory.
    pub(super) fn memory(&self) -> Option<&'a [u8]> {
        match self {
            Bytes::Memory(buf) => Some(buf),
            Bytes::File { .. } => None,
        }
    }
}
