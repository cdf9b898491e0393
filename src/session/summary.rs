//! The summary section of a session file, used only when its CRC in the footer matches: then
//! its chunk index says where every chunk is and what log times it holds, whatever damage the
//! data section took.

use mcap::records::op;

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
