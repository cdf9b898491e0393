//! The linear, damage-tolerant read: walks the top-level records itself, skips damaged ones
//! and stops cleanly at a cut end (crash, power loss).

use mcap::records::op;

use super::decoder::{chunk_reader, Decoder, Failure};
use super::ReadError;
use crate::session::damage::{
    can_follow, framed, known_opcode, le_u64, resync, Damage, RECORD_PREFIX,
};
use crate::session::summary::trusted_summary;

/// A linear read whose damages are dated from the summary's chunk index when it is intact.
pub(super) fn read_linear_dated(buf: &[u8], dec: Decoder) -> Result<Decoder, ReadError> {
    let mut dec = read_linear_into(buf, dec)?;
    if !dec.damages.is_empty() {
        if let Some(summary) = trusted_summary(buf, &dec.file) {
            dec.date_damages(&summary.chunk_indexes);
        }
    }
    Ok(dec)
}

/// Walks the top-level records itself, so that a cut anywhere stops cleanly at the last
/// complete record (and so that the amount read is exact). A damaged record is skipped and
/// reading goes on at the next trustworthy one.
pub(super) fn read_linear(buf: &[u8], file: &str) -> Result<Decoder, ReadError> {
    read_linear_into(buf, Decoder::new(file))
}

pub(super) fn read_linear_into(buf: &[u8], mut dec: Decoder) -> Result<Decoder, ReadError> {
    let mut sans = chunk_reader();
    let mut pos = mcap::MAGIC.len();
    let mut in_data_section = true;
    let mut saw_chunk = false;
    // The damaged chunk whose message indexes (the records right after it) are being read.
    let mut indexing: Option<usize> = None;
    let truncation: Option<(usize, String)> = loop {
        let rest = &buf[pos..];
        if rest.is_empty() {
            break Some((pos, format!("the file ends at byte {pos} with no footer")));
        }
        if rest.len() < RECORD_PREFIX {
            break Some((pos, format!("record header at byte {pos} is cut short")));
        }
        let opcode = rest[0];
        let Some((_, end)) = framed(buf, pos).filter(|_| known_opcode(opcode)) else {
            let why = if known_opcode(opcode) {
                let len = le_u64(&rest[1..]);
                format!(
                    "record (opcode {opcode:#04x}, {len} bytes) at byte {pos} runs past the end \
                     of the file"
                )
            } else {
                format!("record at byte {pos} has no MCAP opcode ({opcode:#04x})")
            };
            if !in_data_section {
                // Past DataEnd only the summary follows: nothing there is a message, so a
                // damaged record costs none; a cut end is still a cut end.
                match resync(buf, pos + 1, saw_chunk, chunk_decodes) {
                    Some(next) => {
                        tracing::warn!(
                            "{}: the summary section is damaged ({why}); every message was read \
                             from the data section",
                            dec.file
                        );
                        pos = next;
                        continue;
                    }
                    None => break Some((pos, why)),
                }
            }
            // A damaged record header, or the file's cut end: the next good record tells.
            match resync(buf, pos + 1, saw_chunk, chunk_decodes) {
                Some(next) => {
                    let i = dec.damage(Damage::new(pos, next - pos, why));
                    // A chunk's message indexes follow it: they tell what it held.
                    indexing = (opcode == op::CHUNK).then_some(i);
                    pos = next;
                    continue;
                }
                None => break Some((pos, why)),
            }
        };
        let record = &buf[pos..end];
        let body = &record[RECORD_PREFIX..];
        if opcode != op::MESSAGE_INDEX {
            indexing = None;
        }
        let result = match opcode {
            op::FOOTER => {
                if buf[end..].starts_with(mcap::MAGIC) {
                    break None;
                }
                break Some((end, "the end magic after the footer is missing".into()));
            }
            op::DATA_END => {
                in_data_section = false;
                Ok(())
            }
            _ if !in_data_section => Ok(()),
            op::CHUNK => {
                saw_chunk = true;
                dec.feed_whole_chunk(&mut sans, record)
            }
            op::MESSAGE_INDEX => {
                if let Some(i) = indexing {
                    let damage = &mut dec.damages[i];
                    if !damage.index.get_or_insert_with(Default::default).add(body) {
                        damage.index = None;
                        indexing = None;
                    }
                }
                Ok(())
            }
            op::SCHEMA | op::CHANNEL | op::MESSAGE => dec.on_record(opcode, body),
            _ => Ok(()),
        };
        match result {
            Ok(()) => {
                dec.settle_neighbours();
                pos = end;
            }
            Err(Failure::Fatal(err)) => return Err(err),
            Err(Failure::Damaged(err)) => {
                sans = chunk_reader();
                let why = format!("record (opcode {opcode:#04x}) at byte {pos}: {err}");
                let i = dec.damage(Damage::new(pos, end - pos, why));
                if can_follow(buf, end) {
                    indexing = (opcode == op::CHUNK).then_some(i);
                    pos = end;
                } else {
                    // Its length is wrong too: look for the next good record inside it.
                    match resync(buf, pos + 1, saw_chunk, chunk_decodes) {
                        Some(next) => {
                            dec.damages[i].length = (next - pos) as u64;
                            pos = next;
                        }
                        None => {
                            let reason = dec.damages.pop().map(|d| d.reason).unwrap_or_default();
                            break Some((pos, reason));
                        }
                    }
                }
            }
        }
    };
    if let Some((bytes_read, reason)) = truncation {
        dec.truncation = Some((bytes_read as u64, reason));
    }
    Ok(dec)
}

/// Whether a whole chunk record decodes (CRC, decompression, records): a resync candidate.
pub(super) fn chunk_decodes(record: &[u8]) -> bool {
    let mut dec = Decoder::new("");
    dec.raw_only = true;
    dec.feed_whole_chunk(&mut chunk_reader(), record).is_ok()
}
