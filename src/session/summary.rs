//! The summary section of a session file, used only when its CRC in the footer matches: then
//! its chunk index says where every chunk is and what log times it holds, whatever damage the
//! data section took.

use std::fs::File;
use std::os::unix::fs::FileExt;

use mcap::records::op;
use mcap::sans_io::summary_reader::{SummaryReadEvent, SummaryReader, SummaryReaderOptions};

use super::damage::{framed, le_u64, RECORD_PREFIX};

/// The summary section when its CRC matches and it parses: then its chunk index tells where
/// each chunk is and what log times it holds, whatever damage the data section took.
pub(crate) fn trusted_summary(buf: &[u8], file: &str) -> Option<mcap::Summary> {
    if !summary_crc_ok(buf) {
        return None;
    }
    match mcap::Summary::read(buf) {
        Ok(summary) => summary,
        Err(err) => {
            tracing::debug!("{file}: no usable summary ({err}); reading linearly");
            None
        }
    }
}

/// Whether the summary section is intact by its CRC (in the footer). Only then is it parsed:
/// the mcap crate trusts the sizes in it, and a corrupt one can make it allocate gigabytes.
/// A file without a summary CRC is read linearly.
fn summary_crc_ok(buf: &[u8]) -> bool {
    const FOOTER_RECORD: usize = RECORD_PREFIX + 20;
    let Some(footer) = buf.len().checked_sub(mcap::MAGIC.len() + FOOTER_RECORD) else {
        return false;
    };
    if !matches!(framed(buf, footer), Some((op::FOOTER, end)) if end == footer + FOOTER_RECORD) {
        return false;
    }
    let summary_start = le_u64(&buf[footer + RECORD_PREFIX..]);
    let crc_at = footer + RECORD_PREFIX + 16;
    let saved = u32::from_le_bytes([
        buf[crc_at],
        buf[crc_at + 1],
        buf[crc_at + 2],
        buf[crc_at + 3],
    ]);
    match usize::try_from(summary_start) {
        Ok(start) if start >= mcap::MAGIC.len() && start <= footer && saved != 0 => {
            crc32fast::hash(&buf[start..crc_at]) == saved
        }
        _ => false,
    }
}

/// As `trusted_summary`, read from the file itself: the footer, then the summary section (its
/// CRC checked first), without reading the data section.
pub(crate) fn trusted_summary_of_file(file: &File, len: u64, name: &str) -> Option<mcap::Summary> {
    const FOOTER_RECORD: u64 = RECORD_PREFIX as u64 + 20;
    let footer = len.checked_sub(mcap::MAGIC.len() as u64 + FOOTER_RECORD)?;
    let mut tail = vec![0u8; (len - footer) as usize];
    file.read_exact_at(&mut tail, footer).ok()?;
    if !matches!(framed(&tail, 0), Some((op::FOOTER, end)) if end == FOOTER_RECORD as usize) {
        return None;
    }
    let summary_start = le_u64(&tail[RECORD_PREFIX..]);
    if summary_start < mcap::MAGIC.len() as u64 || summary_start > footer {
        return None;
    }
    // The summary section, the footer and the end magic: the CRC covers all up to the CRC.
    let mut section = vec![0u8; usize::try_from(len - summary_start).ok()?];
    file.read_exact_at(&mut section, summary_start).ok()?;
    let crc_at = (footer - summary_start) as usize + RECORD_PREFIX + 16;
    let saved = u32::from_le_bytes(section[crc_at..crc_at + 4].try_into().ok()?);
    if saved == 0 || crc32fast::hash(&section[..crc_at]) != saved {
        return None;
    }
    // Parsed as `mcap::Summary::read` parses a whole file, from the verified bytes.
    let mut reader =
        SummaryReader::new_with_options(SummaryReaderOptions::default().with_file_size(len));
    let mut pos = 0u64;
    while let Some(event) = reader.next_event() {
        match event {
            Ok(SummaryReadEvent::ReadRequest(n)) => {
                let available = (len.saturating_sub(pos) as usize).min(n);
                let into = reader.insert(n);
                let read = if pos >= summary_start {
                    let from = usize::try_from(pos - summary_start).unwrap_or(usize::MAX);
                    let part = section.get(from..).unwrap_or_default();
                    let take = available.min(part.len());
                    into[..take].copy_from_slice(&part[..take]);
                    take
                } else {
                    // Only the summary section and the footer are ever requested.
                    match file.read_at(&mut into[..available], pos) {
                        Ok(read) => read,
                        Err(_) => return None,
                    }
                };
                pos += read as u64;
                reader.notify_read(read);
            }
            Ok(SummaryReadEvent::SeekRequest(to)) => {
                pos = match to {
                    std::io::SeekFrom::Start(at) => at,
                    std::io::SeekFrom::End(back) => len.checked_add_signed(back)?,
                    std::io::SeekFrom::Current(by) => pos.checked_add_signed(by)?,
                };
                reader.notify_seeked(pos);
            }
            Err(err) => {
                tracing::debug!("{name}: no usable summary ({err}); reading linearly");
                return None;
            }
        }
    }
    reader.finish()
}
