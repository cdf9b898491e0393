//! One MCAP record parsed from its body, its length fields checked first: the mcap crate
//! allocates a string's or an array's declared length before it finds that the record is
//! shorter, so a damaged length field in a small file would ask for gigabytes.

use mcap::records::{op, Record};
use mcap::McapError;

/// A field of a record's layout (MCAP specification, "Records").
#[derive(Clone, Copy)]
enum Field {
    Fixed(usize),
    /// u32 length, then that many bytes (strings, schema data).
    Bytes32,
    /// u64 length, then that many bytes (chunk records, attachment data).
    Bytes64,
    /// u32 byte length, then string → string entries.
    StringMap,
    /// u32 byte length, then fixed-size entries (message index, offsets, counts).
    Array32,
    /// The rest of the record (a message's payload).
    Rest,
}

use Field::*;

/// The layout of each record whose fields declare lengths; other records have none.
fn layout(opcode: u8) -> &'static [Field] {
    match opcode {
        op::HEADER => &[Bytes32, Bytes32],
        op::SCHEMA => &[Fixed(2), Bytes32, Bytes32, Bytes32],
        op::CHANNEL => &[Fixed(4), Bytes32, Bytes32, StringMap],
        op::MESSAGE => &[Fixed(22), Rest],
        op::CHUNK => &[Fixed(28), Bytes32, Bytes64],
        op::MESSAGE_INDEX => &[Fixed(2), Array32],
        op::CHUNK_INDEX => &[Fixed(32), Array32, Fixed(8), Bytes32, Fixed(16)],
        op::ATTACHMENT => &[Fixed(16), Bytes32, Bytes32, Bytes64, Fixed(4)],
        op::ATTACHMENT_INDEX => &[Fixed(40), Bytes32, Bytes32],
        op::STATISTICS => &[Fixed(42), Array32],
        op::METADATA => &[Bytes32, StringMap],
        op::METADATA_INDEX => &[Fixed(16), Bytes32],
        _ => &[Rest],
    }
}

/// Whether every length field of `body` stays inside it.
pub fn lengths_fit(opcode: u8, body: &[u8]) -> bool {
    let mut at = 0usize;
    for field in layout(opcode) {
        let next = match *field {
            Fixed(n) => at.checked_add(n),
            Bytes32 | Array32 => read_len(body, at, 4).and_then(|n| (at + 4).checked_add(n)),
            Bytes64 => read_len(body, at, 8).and_then(|n| (at + 8).checked_add(n)),
            StringMap => read_len(body, at, 4).and_then(|n| {
                let end = (at + 4).checked_add(n)?;
                map_fits(body.get(at + 4..end)?).then_some(end)
            }),
            Rest => Some(body.len()),
        };
        match next {
            Some(end) if end <= body.len() => at = end,
            _ => return false,
        }
    }
    true
}

/// Parses a record as `mcap::parse_record` does, refusing first one whose length fields run
/// past its end.
pub fn parse(opcode: u8, body: &[u8]) -> Result<Record<'_>, McapError> {
    if !lengths_fit(opcode, body) {
        return Err(McapError::UnexpectedEof);
    }
    mcap::parse_record(opcode, body)
}

fn read_len(body: &[u8], at: usize, width: usize) -> Option<usize> {
    let bytes = body.get(at..at.checked_add(width)?)?;
    let mut le = [0u8; 8];
    le[..width].copy_from_slice(bytes);
    usize::try_from(u64::from_le_bytes(le)).ok()
}

/// String → string entries filling `map` exactly.
fn map_fits(map: &[u8]) -> bool {
    let mut at = 0usize;
    while at < map.len() {
        for _ in 0..2 {
            match read_len(map, at, 4).and_then(|n| (at + 4).checked_add(n)) {
                Some(end) if end <= map.len() => at = end,
                _ => return false,
            }
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    fn string(s: &str) -> Vec<u8> {
        let mut v = (s.len() as u32).to_le_bytes().to_vec();
        v.extend_from_slice(s.as_bytes());
        v
    }

    fn channel(topic_len_field: Option<u32>) -> Vec<u8> {
        let mut body = vec![1, 0, 0, 0];
        let mut topic = string("/tracer/t0/range");
        if let Some(n) = topic_len_field {
            topic[..4].copy_from_slice(&n.to_le_bytes());
        }
        body.extend(topic);
        body.extend(string("json"));
        let entries = [string("k"), string("v")].concat();
        body.extend((entries.len() as u32).to_le_bytes());
        body.extend(entries);
        body
    }

    #[test]
    fn a_well_formed_channel_parses() {
        let body = channel(None);
        assert!(lengths_fit(op::CHANNEL, &body));
        match parse(op::CHANNEL, &body) {
            Ok(Record::Channel(c)) => {
                assert_eq!(c.topic, "/tracer/t0/range");
                assert_eq!(c.metadata.get("k").map(String::as_str), Some("v"));
            }
            other => panic!("expected a channel, got {other:?}"),
        }
    }

    #[test]
    fn a_length_past_the_record_is_refused_before_any_allocation() {
        let body = channel(Some(3_024_841_585));
        assert!(!lengths_fit(op::CHANNEL, &body));
        assert!(matches!(
            parse(op::CHANNEL, &body),
            Err(McapError::UnexpectedEof)
        ));
    }

    #[test]
    fn every_cut_of_a_record_is_refused() {
        let body = channel(None);
        for cut in 0..body.len() {
            assert!(!lengths_fit(op::CHANNEL, &body[..cut]), "cut at {cut}");
        }
    }
}
