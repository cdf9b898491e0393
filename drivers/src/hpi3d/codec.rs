//! HPI-3D bytes <-> frames with no I/O: CRC-8, encoders, and a streaming `Decoder` that
//! resynchronises on the next start byte, so the driver, the emulator and fuzz tests share it.

use std::marker::PhantomData;

use super::frame::{
    DeviceFrame, Distance, HostCommand, HostFrame, Meteo, Status, Velocity, CMD_DISTANCE,
    CMD_METEO, CMD_VELOCITY, DEVICE_FRAME_LEN, HOST_FRAME_LEN, START,
};

/// CRC-8, polynomial 0x31, initial value 0xFF, MSB first, no reflection, no final XOR
/// (the catalogue's CRC-8/NRSC-5).
pub fn crc8(bytes: &[u8]) -> u8 {
    let mut crc: u8 = 0xFF;
    for &b in bytes {
        crc ^= b;
        for _ in 0..8 {
            crc = if crc & 0x80 != 0 {
                (crc << 1) ^ 0x31
            } else {
                crc << 1
            };
        }
    }
    crc
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CodecError {
    #[error("frame of {got} bytes, expected {expected}")]
    Length { got: usize, expected: usize },
    #[error("start byte {0:#04x}, expected 0xaa")]
    Start(u8),
    #[error("crc {got:#04x}, expected {expected:#04x}")]
    Crc { got: u8, expected: u8 },
}

/// A frame type with a fixed wire length; lets one `Decoder` serve both directions.
pub trait WireFrame: Sized {
    const LEN: usize;
    /// Parse a frame whose length, start byte and CRC were already checked.
    fn from_checked(bytes: &[u8]) -> Option<Self>;
    fn to_wire(&self) -> Vec<u8>;
}

fn check(bytes: &[u8], len: usize) -> Result<(), CodecError> {
    if bytes.len() != len {
        return Err(CodecError::Length {
            got: bytes.len(),
            expected: len,
        });
    }
    if bytes[0] != START {
        return Err(CodecError::Start(bytes[0]));
    }
    let expected = crc8(&bytes[..len - 1]);
    if bytes[len - 1] != expected {
        return Err(CodecError::Crc {
            got: bytes[len - 1],
            expected,
        });
    }
    Ok(())
}

fn seal<const N: usize>(mut frame: [u8; N]) -> [u8; N] {
    frame[0] = START;
    frame[N - 1] = crc8(&frame[..N - 1]);
    frame
}

pub fn encode_host(frame: &HostFrame) -> [u8; HOST_FRAME_LEN] {
    let mut b = [0u8; HOST_FRAME_LEN];
    b[1..3].copy_from_slice(&frame.command.code().to_be_bytes());
    b[3..7].copy_from_slice(&frame.data);
    seal(b)
}

pub fn decode_host(bytes: &[u8]) -> Result<HostFrame, CodecError> {
    check(bytes, HOST_FRAME_LEN)?;
    let mut data = [0u8; 4];
    data.copy_from_slice(&bytes[3..7]);
    Ok(HostFrame {
        command: HostCommand::from_code(u16::from_be_bytes([bytes[1], bytes[2]])),
        data,
    })
}

pub fn encode_device(frame: &DeviceFrame) -> [u8; DEVICE_FRAME_LEN] {
    let mut b = [0u8; DEVICE_FRAME_LEN];
    b[1..3].copy_from_slice(&frame.cmd().to_be_bytes());
    let d = &mut b[3..15];
    match frame {
        DeviceFrame::Ack { data, .. } | DeviceFrame::Unknown { data, .. } => {
            d.copy_from_slice(data)
        }
        DeviceFrame::Distance(x) => {
            // Low 7 bytes of the two's complement: the 56-bit field.
            d[0..7].copy_from_slice(&x.position_counts.to_be_bytes()[1..8]);
            d[7..9].copy_from_slice(&x.spare);
            d[9..12].copy_from_slice(&x.status.to_bytes());
        }
        DeviceFrame::Velocity(x) => {
            d[0..4].copy_from_slice(&x.velocity_counts.to_be_bytes());
            d[4..9].copy_from_slice(&x.spare);
            d[9..12].copy_from_slice(&x.status.to_bytes());
        }
        DeviceFrame::Meteo(x) => {
            d[0] = x.sensor;
            d[1..3].copy_from_slice(&x.temperature_centi_c.to_be_bytes());
            d[3] = x.humidity_pct;
            d[4] = x.battery;
            d[5] = x.link;
            d[6..8].copy_from_slice(&x.pressure_deca_pa.to_be_bytes());
            d[8..12].copy_from_slice(&x.spare);
        }
    }
    seal(b)
}

pub fn decode_device(bytes: &[u8]) -> Result<DeviceFrame, CodecError> {
    check(bytes, DEVICE_FRAME_LEN)?;
    let cmd = u16::from_be_bytes([bytes[1], bytes[2]]);
    let mut d = [0u8; 12];
    d.copy_from_slice(&bytes[3..15]);
    let status = Status::from_bytes([d[9], d[10], d[11]]);
    Ok(match cmd {
        CMD_DISTANCE => {
            let mut wide = [0u8; 8];
            wide[1..8].copy_from_slice(&d[0..7]);
            // Shift up then arithmetic-shift down to sign-extend the 56-bit field.
            let position_counts = (i64::from_be_bytes(wide) << 8) >> 8;
            DeviceFrame::Distance(Distance {
                position_counts,
                spare: [d[7], d[8]],
                status,
            })
        }
        CMD_VELOCITY => DeviceFrame::Velocity(Velocity {
            velocity_counts: i32::from_be_bytes([d[0], d[1], d[2], d[3]]),
            spare: [d[4], d[5], d[6], d[7], d[8]],
            status,
        }),
        CMD_METEO => DeviceFrame::Meteo(Meteo {
            sensor: d[0],
            temperature_centi_c: i16::from_be_bytes([d[1], d[2]]),
            humidity_pct: d[3],
            battery: d[4],
            link: d[5],
            pressure_deca_pa: u16::from_be_bytes([d[6], d[7]]),
            spare: [d[8], d[9], d[10], d[11]],
        }),
        _ => match HostCommand::known(cmd) {
            Some(command) => DeviceFrame::Ack { command, data: d },
            None => DeviceFrame::Unknown { cmd, data: d },
        },
    })
}

impl WireFrame for HostFrame {
    const LEN: usize = HOST_FRAME_LEN;
    fn from_checked(bytes: &[u8]) -> Option<Self> {
        decode_host(bytes).ok()
    }
    fn to_wire(&self) -> Vec<u8> {
        encode_host(self).to_vec()
    }
}

impl WireFrame for DeviceFrame {
    const LEN: usize = DEVICE_FRAME_LEN;
    fn from_checked(bytes: &[u8]) -> Option<Self> {
        decode_device(bytes).ok()
    }
    fn to_wire(&self) -> Vec<u8> {
        encode_device(self).to_vec()
    }
}

/// What a `Decoder` threw away, for fault reports.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DecoderStats {
    pub frames_ok: u64,
    /// Candidate frames (a start byte with enough bytes behind it) whose CRC failed, counted
    /// once per frame length so the false starts inside one corrupted frame count once.
    pub frames_corrupted: u64,
    /// Every byte discarded: garbage before a start byte and the bytes of rejected candidates.
    pub bytes_skipped: u64,
}

/// Streaming decoder: feed arbitrary chunks, get whole frames.
///
/// A frame is accepted on its CRC alone; on a failure the decoder drops one byte and looks
/// for the next 0xAA. A false start inside corrupted data passes the CRC with probability
/// 1/256 and then swallows the start of the real frame after it; CRC-8 gives no better.
#[derive(Debug)]
pub struct Decoder<F: WireFrame> {
    buf: Vec<u8>,
    /// Bytes still inside the span of the last corrupted candidate (not counted again).
    shadow: usize,
    stats: DecoderStats,
    _frame: PhantomData<fn() -> F>,
}

impl<F: WireFrame> Default for Decoder<F> {
    fn default() -> Self {
        Self::new()
    }
}

/// Host side: decodes 16-byte device frames.
pub type DeviceDecoder = Decoder<DeviceFrame>;
/// Device side (emulator): decodes 8-byte host frames.
pub type HostDecoder = Decoder<HostFrame>;

impl<F: WireFrame> Decoder<F> {
    pub fn new() -> Self {
        Decoder {
            buf: Vec::with_capacity(4 * F::LEN),
            shadow: 0,
            stats: DecoderStats::default(),
            _frame: PhantomData,
        }
    }

    pub fn stats(&self) -> DecoderStats {
        self.stats
    }

    /// Bytes held back waiting for the rest of a frame (always fewer than one frame).
    pub fn pending(&self) -> usize {
        self.buf.len()
    }

    /// Add bytes and return every frame they complete.
    pub fn feed(&mut self, bytes: &[u8]) -> Vec<F> {
        let mut out = Vec::new();
        self.feed_into(bytes, &mut out);
        out
    }

    /// As `feed`, appending to `out` (no allocation per call once `out` has grown).
    pub fn feed_into(&mut self, bytes: &[u8], out: &mut Vec<F>) {
        self.buf.extend_from_slice(bytes);
        let mut pos = 0;
        loop {
            match self.buf[pos..].iter().position(|&b| b == START) {
                None => {
                    let n = self.buf.len() - pos;
                    self.skip(n);
                    pos = self.buf.len();
                    break;
                }
                Some(k) => {
                    self.skip(k);
                    pos += k;
                }
            }
            if self.buf.len() - pos < F::LEN {
                break;
            }
            let candidate = &self.buf[pos..pos + F::LEN];
            let frame = if crc8(&candidate[..F::LEN - 1]) == candidate[F::LEN - 1] {
                F::from_checked(candidate)
            } else {
                None
            };
            match frame {
                Some(frame) => {
                    out.push(frame);
                    self.stats.frames_ok += 1;
                    self.shadow = 0;
                    pos += F::LEN;
                }
                None => {
                    if self.shadow == 0 {
                        self.stats.frames_corrupted += 1;
                        self.shadow = F::LEN;
                    }
                    self.skip(1);
                    pos += 1;
                }
            }
        }
        self.buf.drain(..pos);
    }

    fn skip(&mut self, n: usize) {
        self.stats.bytes_skipped += n as u64;
        self.shadow = self.shadow.saturating_sub(n);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc8_known_answers() {
        // CRC-8/NRSC-5 check value, and the Sensirion example (same parameters).
        assert_eq!(crc8(b"123456789"), 0xF7);
        assert_eq!(crc8(&[0xBE, 0xEF]), 0x92);
        assert_eq!(crc8(&[]), 0xFF);
    }

    #[test]
    fn host_command_bytes() {
        let b = encode_host(&HostFrame::new(HostCommand::Home));
        assert_eq!(&b[..7], &[0xAA, 0xB0, 0x48, 0, 0, 0, 0]);
        assert_eq!(b[7], crc8(&b[..7]));
        assert_eq!(decode_host(&b).unwrap(), HostFrame::new(HostCommand::Home));
    }

    #[test]
    fn distance_sign_extension_and_units() {
        let f = DeviceFrame::Distance(Distance {
            position_counts: -12_345_678_901,
            spare: [0, 0],
            status: Status::ok(200),
        });
        let b = encode_device(&f);
        assert_eq!(&b[..3], &[0xAA, 0xB0, 0x15]);
        // Byte 10 of the data has the laser-ready and signal-ok bits.
        assert_eq!(b[3 + 10], 0b1001);
        let DeviceFrame::Distance(d) = decode_device(&b).unwrap() else {
            panic!("not a distance frame")
        };
        assert_eq!(d.position_counts, -12_345_678_901);
        assert!((d.position_m() + 1.2345678901).abs() < 1e-15);
        assert!(d.status.tracking());
        let extreme = Distance::counts_from_m(1e9);
        assert_eq!(extreme, crate::hpi3d::frame::POSITION_MAX_COUNTS);
    }

    #[test]
    fn meteo_units() {
        let m = Meteo {
            sensor: 0,
            temperature_centi_c: 2012,
            humidity_pct: 45,
            battery: 90,
            link: 100,
            pressure_deca_pa: 10132,
            spare: [0; 4],
        };
        let DeviceFrame::Meteo(back) =
            decode_device(&encode_device(&DeviceFrame::Meteo(m))).unwrap()
        else {
            panic!("not meteo")
        };
        assert_eq!(back, m);
        assert!((back.temperature_k() - 293.27).abs() < 1e-9);
        assert!((back.pressure_pa() - 101_320.0).abs() < 1e-9);
    }

    #[test]
    fn ack_and_unknown() {
        let ack = encode_device(&DeviceFrame::ack(HostCommand::DistanceOn));
        assert_eq!(
            decode_device(&ack).unwrap(),
            DeviceFrame::ack(HostCommand::DistanceOn)
        );
        let unknown = DeviceFrame::Unknown {
            cmd: 0x1234,
            data: [7; 12],
        };
        assert_eq!(decode_device(&encode_device(&unknown)).unwrap(), unknown);
    }

    #[test]
    fn bad_crc_resynchronises() {
        let a = encode_device(&DeviceFrame::ack(HostCommand::Home));
        let mut bad = encode_device(&DeviceFrame::ack(HostCommand::StopAll));
        bad[5] ^= 0x40;
        let mut bytes = vec![1, 2, 3];
        bytes.extend_from_slice(&bad);
        bytes.extend_from_slice(&a);
        let mut d = DeviceDecoder::new();
        assert_eq!(d.feed(&bytes), vec![DeviceFrame::ack(HostCommand::Home)]);
        let s = d.stats();
        assert_eq!(s.frames_ok, 1);
        assert_eq!(s.frames_corrupted, 1);
        assert_eq!(s.bytes_skipped, 3 + 16);
    }
}

#[cfg(test)]
mod proptests {
    use proptest::prelude::*;
    use proptest::test_runner::RngSeed;

    use super::*;
    use crate::hpi3d::frame::{POSITION_MAX_COUNTS, POSITION_MIN_COUNTS};

    fn config() -> ProptestConfig {
        // A fixed seed keeps CI deterministic; the properties hold for any seed.
        ProptestConfig {
            cases: 256,
            rng_seed: RngSeed::Fixed(0x4850_4933),
            failure_persistence: None,
            ..ProptestConfig::default()
        }
    }

    fn status() -> impl Strategy<Value = Status> {
        (any::<[u8; 3]>()).prop_map(Status::from_bytes)
    }

    fn device_frame() -> impl Strategy<Value = DeviceFrame> {
        prop_oneof![
            (0..HostCommand::KNOWN.len(), any::<[u8; 12]>()).prop_map(|(i, data)| {
                DeviceFrame::Ack {
                    command: HostCommand::KNOWN[i],
                    data,
                }
            }),
            (
                POSITION_MIN_COUNTS..=POSITION_MAX_COUNTS,
                any::<[u8; 2]>(),
                status()
            )
                .prop_map(|(position_counts, spare, status)| {
                    DeviceFrame::Distance(Distance {
                        position_counts,
                        spare,
                        status,
                    })
                }),
            (any::<i32>(), any::<[u8; 5]>(), status()).prop_map(
                |(velocity_counts, spare, status)| {
                    DeviceFrame::Velocity(Velocity {
                        velocity_counts,
                        spare,
                        status,
                    })
                }
            ),
            any::<([u8; 6], u16, [u8; 4])>().prop_map(|(b, p, spare)| {
                DeviceFrame::Meteo(Meteo {
                    sensor: b[0],
                    temperature_centi_c: i16::from_be_bytes([b[1], b[2]]),
                    humidity_pct: b[3],
                    battery: b[4],
                    link: b[5],
                    pressure_deca_pa: p,
                    spare,
                })
            }),
            (any::<u16>(), any::<[u8; 12]>()).prop_filter_map("documented cmd", |(cmd, data)| {
                let documented = HostCommand::known(cmd).is_some()
                    || [CMD_DISTANCE, CMD_VELOCITY, CMD_METEO].contains(&cmd);
                (!documented).then_some(DeviceFrame::Unknown { cmd, data })
            }),
        ]
    }

    fn host_frame() -> impl Strategy<Value = HostFrame> {
        (any::<u16>(), any::<[u8; 4]>()).prop_map(|(code, data)| HostFrame {
            command: HostCommand::from_code(code),
            data,
        })
    }

    fn wire<F: WireFrame>(frames: &[F]) -> Vec<u8> {
        frames.iter().flat_map(|f| f.to_wire()).collect()
    }

    /// Feed `bytes` cut at the given positions (taken modulo the length).
    fn feed_split<F: WireFrame>(bytes: &[u8], cuts: &[usize]) -> (Vec<F>, DecoderStats) {
        let mut cuts: Vec<usize> = cuts
            .iter()
            .map(|c| if bytes.is_empty() { 0 } else { c % bytes.len() })
            .collect();
        cuts.push(0);
        cuts.push(bytes.len());
        cuts.sort_unstable();
        let mut d = Decoder::<F>::new();
        let mut out = Vec::new();
        for w in cuts.windows(2) {
            d.feed_into(&bytes[w[0]..w[1]], &mut out);
        }
        (out, d.stats())
    }

    /// `expected` frames missing from `got` (in order), and frames of `got` not in `expected`.
    fn lost_and_spurious(expected: &[DeviceFrame], got: &[DeviceFrame]) -> (Vec<usize>, usize) {
        let mut lost = Vec::new();
        let mut spurious = 0;
        let mut j = 0;
        for (i, e) in expected.iter().enumerate() {
            // Skip spurious frames until this expected one, if it is there at all.
            match got[j..].iter().position(|g| g == e) {
                Some(k) => {
                    spurious += k;
                    j += k + 1;
                }
                None => lost.push(i),
            }
        }
        spurious += got.len() - j;
        (lost, spurious)
    }

    proptest! {
        #![proptest_config(config())]

        #[test]
        fn device_roundtrip(f in device_frame()) {
            let b = encode_device(&f);
            prop_assert_eq!(decode_device(&b).unwrap(), f);
            prop_assert_eq!(encode_device(&decode_device(&b).unwrap()), b);
        }

        #[test]
        fn host_roundtrip(f in host_frame()) {
            let b = encode_host(&f);
            prop_assert_eq!(decode_host(&b).unwrap(), f);
        }

        #[test]
        fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..600),
                                    cuts in proptest::collection::vec(any::<usize>(), 0..8)) {
            let (frames, stats) = feed_split::<DeviceFrame>(&bytes, &cuts);
            prop_assert!(stats.bytes_skipped as usize + 16 * frames.len() <= bytes.len());
            let _ = feed_split::<HostFrame>(&bytes, &cuts);
        }

        #[test]
        fn any_split_decodes_identically(frames in proptest::collection::vec(device_frame(), 0..20),
                                         cuts in proptest::collection::vec(any::<usize>(), 0..30)) {
            let bytes = wire(&frames);
            let (got, stats) = feed_split::<DeviceFrame>(&bytes, &cuts);
            prop_assert_eq!(&got, &frames);
            prop_assert_eq!(stats.bytes_skipped, 0);
            prop_assert_eq!(stats.frames_corrupted, 0);
        }

        #[test]
        fn host_frames_any_split(frames in proptest::collection::vec(host_frame(), 0..20),
                                 cuts in proptest::collection::vec(any::<usize>(), 0..30)) {
            let (got, _) = feed_split::<HostFrame>(&wire(&frames), &cuts);
            prop_assert_eq!(got, frames);
        }

        #[test]
        fn garbage_between_frames(
            items in proptest::collection::vec(
                (device_frame(), proptest::collection::vec(any::<u8>(), 0..40)), 0..15),
            cuts in proptest::collection::vec(any::<usize>(), 0..10),
        ) {
            let mut bytes = Vec::new();
            let mut frames = Vec::new();
            for (f, garbage) in &items {
                bytes.extend_from_slice(garbage);
                bytes.extend_from_slice(&encode_device(f));
                frames.push(*f);
            }
            let (got, _) = feed_split::<DeviceFrame>(&bytes, &cuts);
            let (lost, spurious) = lost_and_spurious(&frames, &got);
            // A real frame is lost only when a false start in the garbage passed the CRC
            // (p = 1/256) and swallowed its start byte.
            prop_assert!(lost.len() <= spurious, "lost {:?}, spurious {}", lost, spurious);
            if !bytes.is_empty() && items.iter().all(|(_, g)| !g.contains(&START)) {
                prop_assert_eq!(&got, &frames);
            }
        }

        #[test]
        fn corrupted_byte_loses_only_touched_frames(
            frames in proptest::collection::vec(device_frame(), 1..15),
            at in any::<usize>(),
            flip in 1u8..=255,
            cuts in proptest::collection::vec(any::<usize>(), 0..10),
        ) {
            let mut bytes = wire(&frames);
            let at = at % bytes.len();
            bytes[at] ^= flip;
            let touched = at / DEVICE_FRAME_LEN;
            let (got, stats) = feed_split::<DeviceFrame>(&bytes, &cuts);
            let (lost, spurious) = lost_and_spurious(&frames, &got);
            // CRC-8 catches every error within 8 bits, so the touched frame is always lost;
            // a later one only if a false start (p = 1/256) swallowed it.
            prop_assert!(lost.contains(&touched));
            prop_assert!(lost.iter().all(|&i| i >= touched));
            prop_assert!(lost.len() <= 1 + spurious, "lost {:?}, spurious {}", lost, spurious);
            prop_assert!(stats.frames_corrupted <= 1 + spurious as u64 || at % DEVICE_FRAME_LEN == 0);
        }
    }
}
