//! The checking bodies of the decoders' fuzz targets (`fuzz/`), shared with the
//! seeded fuzz-style tests that run on stable Rust: each takes arbitrary bytes and
//! panics if a decoder misbehaves on them. A test harness, not part of the API: its
//! asserts are the point.

mod capture;

pub use capture::{check_capture, read_capture, sample_capture};

use crate::TriangleFlags;
use crate::pose::Pose;
use crate::sensor::RangeNoise;
use crate::txl1::{
    self, HeaderCheck, MAGIC, MAX_FRAME_LEN, Txl1Counters, Txl1Decoder, Txl1Frame, Txl1Step,
    WORK_UNITS_PER_BYTE,
};
use crate::wire::client::FrameReader;
use crate::wire::{self, Limits, Message, Texture, TextureFormat, WireScan};

/// A small deterministic generator (splitmix64), so that an input fully decides a run.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// A number in `0..n` (0 when `n` is 0).
    pub fn below(&mut self, n: u64) -> u64 {
        if n == 0 { 0 } else { self.next_u64() % n }
    }
}

/// Reads an input a byte at a time, then zeros.
struct Script<'a>(&'a [u8]);

impl Script<'_> {
    fn byte(&mut self) -> u8 {
        match self.0.split_first() {
            Some((&b, rest)) => {
                self.0 = rest;
                b
            }
            None => 0,
        }
    }

    fn u16(&mut self) -> u16 {
        u16::from_le_bytes([self.byte(), self.byte()])
    }

    fn take(&mut self, n: usize) -> &[u8] {
        let (now, rest) = self.0.split_at(n.min(self.0.len()));
        self.0 = rest;
        now
    }
}

/// One piece of a TXL1 test stream.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Piece {
    /// A valid frame.
    Valid {
        width: u16,
        height: u16,
        intensity: bool,
        seq: u32,
    },
    /// A frame with one byte after its header xor-ed (payload or CRC): a CRC error.
    CorruptCrc {
        width: u16,
        height: u16,
        seq: u32,
        at: usize,
        xor: u8,
    },
    /// A frame with one byte anywhere xor-ed (its header included).
    Damaged {
        width: u16,
        height: u16,
        seq: u32,
        at: usize,
        xor: u8,
    },
    /// A valid header alone, claiming a frame of any size up to the largest.
    Claims {
        width: u16,
        height: u16,
        intensity: bool,
    },
    /// The magic repeated.
    MagicFlood(usize),
    /// A header with one field out of range (`field` picks which).
    BadHeader { field: u8 },
    /// The first `keep` bytes of a valid frame.
    Truncated {
        width: u16,
        height: u16,
        seq: u32,
        keep: usize,
    },
    /// `count` valid headers, each starting 12 bytes after the previous (inside its
    /// header), all claiming frames of the given size.
    Nested {
        count: usize,
        width: u16,
        height: u16,
        intensity: bool,
    },
    /// Bytes as they are.
    Noise(Vec<u8>),
}

/// A frame whose pixel values follow from its seq.
pub fn test_frame(width: u16, height: u16, intensity: bool, seq: u32) -> Txl1Frame {
    let pixels = usize::from(width) * usize::from(height);
    let mut rng = Rng::new(u64::from(seq) ^ (u64::from(width) << 32) ^ (u64::from(height) << 48));
    Txl1Frame {
        width,
        height,
        seq,
        timestamp_ns: u64::from(seq) * 1_000_000,
        range_unit_um: 1000,
        ranges: (0..pixels).map(|_| rng.next_u64() as u16).collect(),
        intensities: intensity.then(|| (0..pixels).map(|_| rng.next_u64() as u16).collect()),
    }
}

/// A header claiming a `width` x `height` frame (bytes 12.. are seq 7, timestamp 0,
/// unit 1000).
pub fn header(width: u16, height: u16, intensity: bool) -> Vec<u8> {
    let mut h = MAGIC.to_vec();
    h.push(txl1::VERSION);
    h.push(u8::from(intensity));
    h.extend_from_slice(&width.to_le_bytes());
    h.extend_from_slice(&height.to_le_bytes());
    h.extend_from_slice(&[0, 0]);
    h.extend_from_slice(&7u32.to_le_bytes());
    h.extend_from_slice(&0u64.to_le_bytes());
    h.extend_from_slice(&1000u32.to_le_bytes());
    h
}

fn small_side(s: u16) -> u16 {
    1 + s % 8
}

impl Piece {
    /// The piece's bytes.
    pub fn bytes(&self) -> Vec<u8> {
        match *self {
            Self::Valid {
                width,
                height,
                intensity,
                seq,
            } => test_frame(width, height, intensity, seq).encode(),
            Self::CorruptCrc {
                width,
                height,
                seq,
                at,
                xor,
            } => {
                let mut b = test_frame(width, height, false, seq).encode();
                let span = b.len() - txl1::HEADER_LEN;
                b[txl1::HEADER_LEN + at % span] ^= xor.max(1);
                b
            }
            Self::Damaged {
                width,
                height,
                seq,
                at,
                xor,
            } => {
                let mut b = test_frame(width, height, true, seq).encode();
                let n = b.len();
                b[at % n] ^= xor;
                b
            }
            Self::Claims {
                width,
                height,
                intensity,
            } => header(width, height, intensity),
            Self::MagicFlood(n) => MAGIC.repeat(n),
            Self::BadHeader { field } => {
                let mut h = header(4, 4, false);
                match field % 6 {
                    0 => h[4] = 2,        // version
                    1 => h[5] = 0x02,     // unknown flag
                    2 => h[6..8].fill(0), // zero width
                    3 => h[8..10].copy_from_slice(&(txl1::MAX_SIDE + 1).to_le_bytes()),
                    4 => h[10] = 1,         // reserved
                    _ => h[24..28].fill(0), // zero unit
                }
                h
            }
            Self::Truncated {
                width,
                height,
                seq,
                keep,
            } => {
                let mut b = test_frame(width, height, false, seq).encode();
                b.truncate(keep % b.len());
                b
            }
            Self::Nested {
                count,
                width,
                height,
                intensity,
            } => {
                let mut b = Vec::with_capacity(12 * count + 16);
                for _ in 0..count {
                    b.extend_from_slice(&header(width, height, intensity)[..12]);
                }
                b.extend_from_slice(&header(width, height, intensity)[12..]);
                b
            }
            Self::Noise(ref bytes) => bytes.clone(),
        }
    }
}

/// The bytes of `pieces`, one after the other.
pub fn stream_of(pieces: &[Piece]) -> Vec<u8> {
    pieces.iter().flat_map(Piece::bytes).collect()
}

/// Pieces read from an input, a few bytes each, at most 64 of them.
pub fn pieces_from(data: &[u8]) -> Vec<Piece> {
    let mut s = Script(data);
    let mut pieces = Vec::new();
    while !s.0.is_empty() && pieces.len() < 64 {
        let op = s.byte();
        let (w, h) = (small_side(s.u16()), small_side(s.u16()));
        let seq = u32::from(s.byte());
        pieces.push(match op % 9 {
            0 => Piece::Valid {
                width: w,
                height: h,
                intensity: op & 0x10 != 0,
                seq,
            },
            1 => Piece::CorruptCrc {
                width: w,
                height: h,
                seq,
                at: usize::from(s.u16()),
                xor: s.byte(),
            },
            2 => Piece::Damaged {
                width: w,
                height: h,
                seq,
                at: usize::from(s.u16()),
                xor: s.byte(),
            },
            3 => Piece::Claims {
                width: 1 + s.u16() % txl1::MAX_SIDE,
                height: 1 + s.u16() % txl1::MAX_SIDE,
                intensity: op & 0x10 != 0,
            },
            4 => Piece::MagicFlood(usize::from(s.u16()) % 4096),
            5 => Piece::BadHeader { field: s.byte() },
            6 => Piece::Truncated {
                width: w,
                height: h,
                seq,
                keep: usize::from(s.u16()),
            },
            7 => Piece::Nested {
                count: usize::from(s.byte()) % 64,
                width: w,
                height: h,
                intensity: op & 0x10 != 0,
            },
            _ => {
                let n = usize::from(s.byte() % 64);
                Piece::Noise(s.take(n).to_vec())
            }
        });
    }
    pieces
}

/// Streams up to this long are also decoded by [`reference_decode`] and compared.
pub const REFERENCE_LIMIT: usize = 64 * 1024;

/// What decoding a whole stream gave.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Decoded {
    pub frames: Vec<Txl1Frame>,
    pub counters: Txl1Counters,
    /// Bytes still held, waiting for more.
    pub buffered: usize,
}

/// The receiver rules (`spec/serial-lidar-protocol.md`) applied to a whole stream at
/// once, as plainly as possible (each span hashed in full, so quadratic on hostile
/// input): the model the streaming decoder is checked against.
pub fn reference_decode(s: &[u8]) -> Decoded {
    let mut out = Decoded {
        frames: Vec::new(),
        counters: Txl1Counters::default(),
        buffered: 0,
    };
    let mut last_seq = None;
    let mut pos = 0;
    // Bytes before this offset belong to a frame dropped for its CRC.
    let mut bad_until = 0;
    fn skip(pos: &mut usize, n: usize, bad_until: usize, c: &mut Txl1Counters) {
        let bad = bad_until.saturating_sub(*pos).min(n);
        c.bytes_in_bad_frames += bad as u64;
        c.bytes_skipped += (n - bad) as u64;
        *pos += n;
    }
    loop {
        let rest = &s[pos..];
        match rest.windows(MAGIC.len()).position(|w| w == MAGIC) {
            Some(p) => {
                skip(&mut pos, p, bad_until, &mut out.counters);
                bad_until = bad_until.min(pos);
            }
            None => {
                let keep = (1..MAGIC.len())
                    .rev()
                    .find(|&k| rest.ends_with(&MAGIC[..k]))
                    .unwrap_or(0);
                skip(&mut pos, rest.len() - keep, bad_until, &mut out.counters);
                break;
            }
        }
        match txl1::header_check(&s[pos..]) {
            HeaderCheck::Incomplete => break,
            HeaderCheck::Invalid => {
                out.counters.bad_headers += 1;
                skip(&mut pos, 1, bad_until, &mut out.counters);
            }
            HeaderCheck::Valid(total) => {
                let Some(frame) = s.get(pos..pos + total) else {
                    break;
                };
                let crc_at = total - txl1::CRC_LEN;
                let stored = u32::from_le_bytes([
                    frame[crc_at],
                    frame[crc_at + 1],
                    frame[crc_at + 2],
                    frame[crc_at + 3],
                ]);
                if crc32fast::hash(&frame[MAGIC.len()..crc_at]) != stored {
                    out.counters.crc_errors += 1;
                    bad_until = pos + total;
                    skip(&mut pos, MAGIC.len(), bad_until, &mut out.counters);
                    continue;
                }
                let f = txl1::decode_valid(frame);
                txl1::note_seq(&mut out.counters, &mut last_seq, f.seq);
                out.frames.push(f);
                pos += total;
            }
        }
    }
    out.buffered = s.len() - pos;
    out
}

/// Feeds `stream` to a [`Txl1Decoder`] in chunks of sizes drawn from `seed`, with work
/// budgets drawn likewise, checking as it goes that the buffer stays bounded; returns
/// what it decoded.
pub fn decode_in_chunks(decoder: &mut Txl1Decoder, stream: &[u8], seed: u64) -> Vec<Txl1Frame> {
    let mut rng = Rng::new(seed);
    let mut frames = Vec::new();
    let mut rest = stream;
    while !rest.is_empty() {
        let n = match rng.below(4) {
            0 => 1 + rng.below(8),
            1 => 1 + rng.below(512),
            2 => 1 + rng.below(16 * 1024),
            _ => 1 + rng.below(rest.len() as u64),
        };
        let (chunk, later) = rest.split_at((n as usize).min(rest.len()));
        rest = later;
        assert!(
            decoder.buffered() < MAX_FRAME_LEN,
            "held {} bytes between reads",
            decoder.buffered()
        );
        decoder.push(chunk);
        let budget = if rng.below(2) == 0 {
            u64::MAX
        } else {
            1 + rng.below(4096)
        };
        loop {
            match decoder.decode(budget) {
                Txl1Step::Frame(f) => frames.push(f),
                Txl1Step::NeedBytes => break,
                Txl1Step::Paused => {}
            }
        }
        assert!(
            decoder.buffered() < MAX_FRAME_LEN,
            "held {} bytes",
            decoder.buffered()
        );
        let before = decoder.work_units();
        assert_eq!(decoder.decode(u64::MAX), Txl1Step::NeedBytes);
        assert_eq!(
            decoder.work_units(),
            before,
            "a call with no new bytes does no work"
        );
    }
    frames
}

/// Checks the TXL1 decoder on one stream: no panic, bounded buffer, work linear in the
/// bytes, valid frames that encode back to themselves, and (for short streams) the
/// same frames, counters and leftover as [`reference_decode`] on the whole stream.
pub fn check_txl1_stream(stream: &[u8], seed: u64) -> Decoded {
    let mut d = Txl1Decoder::new();
    let frames = decode_in_chunks(&mut d, stream, seed);
    let bound = WORK_UNITS_PER_BYTE * stream.len() as u64;
    assert!(
        d.work_units() <= bound,
        "{} work units for {} bytes",
        d.work_units(),
        stream.len()
    );
    for f in &frames {
        let mut again = Txl1Decoder::new();
        again.push(&f.encode());
        assert_eq!(
            again.next_frame().as_ref(),
            Some(f),
            "a decoded frame re-encodes to itself"
        );
    }
    let got = Decoded {
        frames,
        counters: d.counters(),
        buffered: d.buffered(),
    };
    if stream.len() <= REFERENCE_LIMIT {
        assert_eq!(
            got,
            reference_decode(stream),
            "the streaming decoder follows the rules"
        );
    }
    got
}

/// The `txl1_decoder` fuzz target: the first byte picks raw bytes or a script of
/// [`Piece`]s, the next two seed the chunking.
pub fn check_txl1(data: &[u8]) {
    let mut s = Script(data);
    let mode = s.byte();
    let seed = u64::from(s.u16());
    let stream = if mode & 1 == 0 {
        s.0.to_vec()
    } else {
        stream_of(&pieces_from(s.0))
    };
    check_txl1_stream(&stream, seed);
}

/// Messages of every kind, for seeds and mutations.
pub fn sample_messages() -> Vec<Message> {
    let scan = WireScan {
        id: 3,
        world_from_scan: Pose::translation(1.0, -2.0, 0.5),
        timestamp_ns: 42,
        seq: 9,
        grid_width: 2,
        grid_height: 2,
        scan_from_lidar: Pose::identity(),
        cop_m: [0.0, 0.1, 0.2],
        range_noise: RangeNoise {
            sigma_m: 0.01,
            sigma_per_m: 0.001,
        },
        vertices: vec![
            [0.0, 0.0, 1.0],
            [1.0, 0.0, 1.0],
            [0.0, 1.0, 1.0],
            [1.0, 1.0, 1.5],
        ],
        tex_coords: vec![[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]],
        vertex_textured: vec![true, true, false, true],
        vertex_pixel: vec![0, 1, 2, 3],
        triangles: vec![[0, 1, 2], [1, 3, 2]],
        triangle_accuracy: vec![0.5, 1.0],
        triangle_flags: vec![TriangleFlags(0), TriangleFlags(1)],
        texture: Texture {
            format: TextureFormat::Rgb8,
            width: 1,
            height: 1,
            timestamp_ns: 42,
            data: vec![10, 20, 30],
        },
    };
    vec![
        Message::ClientHello {
            version: wire::PROTOCOL_VERSION,
            token: "secret".into(),
            client_name: "viewer".into(),
        },
        Message::ServerHello {
            version: 1,
            server_name: "texeld".into(),
            session_name: "lab".into(),
        },
        Message::Refused {
            reason: "wrong token".into(),
        },
        Message::ModelReset { scan_count: 3 },
        Message::SnapshotComplete { scan_count: 3 },
        Message::ScanAdded(Box::new(scan)),
        Message::PoseRevised {
            id: 7,
            world_from_scan: Pose::translation(1.0, 2.0, 3.0),
        },
        Message::Status(Box::default()),
        Message::Goodbye {
            reason: "shutting down".into(),
        },
        Message::ScanListed {
            id: 3,
            listing: crate::model::ScanListing {
                timestamp_ns: 42,
                bounds_min_m: [0.0, 0.0, 1.0],
                bounds_max_m: [1.0, 1.0, 1.5],
                cop_m: [0.0, 0.1, 0.2],
                priority: 0.5,
                encoded_bytes: 1234,
            },
            world_from_scan: Pose::translation(1.0, -2.0, 0.5),
        },
        Message::ScanWithdrawn { id: 3 },
        Message::ScanExposure {
            id: 3,
            exposure: crate::EoExposure {
                exposure_time_s: 0.008,
                gain: 2.0,
            },
        },
        Message::EoResponse(Box::new(crate::radiance::EoResponse::srgb())),
        Message::ScanUnavailable {
            id: 8,
            reason: "scan 8 is not in the served model".into(),
        },
        Message::RequestScan { id: 8 },
        Message::TileListed {
            id: crate::tile::TileId {
                lod: 2,
                x: -3,
                y: 4,
            },
            listing: crate::tile::TileListing {
                revision: 5,
                bounds_min_m: [-25.6, 51.2, -1.0],
                bounds_max_m: [0.0, 76.8, 12.0],
                geometric_error_m: 0.25,
                triangles: 100,
                encoded_bytes: 2000,
            },
        },
        Message::TileWithdrawn {
            id: crate::tile::TileId { lod: 0, x: 0, y: 0 },
        },
        Message::TileData(Box::new(wire::WireTile {
            id: crate::tile::TileId {
                lod: 1,
                x: 9,
                y: -9,
            },
            revision: 5,
            data: b"TXLT".to_vec(),
        })),
        Message::TileUnavailable {
            id: crate::tile::TileId {
                lod: 1,
                x: 9,
                y: -9,
            },
            reason: "tile 1/9/-9 is not in the tree".into(),
        },
        Message::RequestTile {
            id: crate::tile::TileId {
                lod: 1,
                x: 9,
                y: -9,
            },
        },
    ]
}

/// The poses a message carries.
#[cfg(test)]
fn poses(message: &Message) -> Vec<&Pose> {
    match message {
        Message::PoseRevised {
            world_from_scan, ..
        } => vec![world_from_scan],
        Message::ScanAdded(scan) => vec![&scan.world_from_scan, &scan.scan_from_lidar],
        Message::ScanListed {
            world_from_scan, ..
        } => vec![world_from_scan],
        _ => Vec::new(),
    }
}

/// A decoded message encodes, and its encoding decodes to a message that encodes to
/// the same bytes (bytes compared, as floats may be NaN).
fn check_round_trip(message: &Message, limits: &Limits) {
    let bytes = match message.encode() {
        Ok(b) => b,
        Err(e) => panic!("a decoded {} does not encode: {e}", message.kind_name()),
    };
    match wire::decode_frame(&bytes, limits) {
        Ok(Some((again, used))) => {
            assert_eq!(
                used,
                bytes.len(),
                "{}: the whole encoding is one frame",
                message.kind_name()
            );
            match again.encode() {
                Ok(b) => assert_eq!(b, bytes, "{} round-trips", message.kind_name()),
                Err(e) => panic!("a re-decoded {} does not encode: {e}", message.kind_name()),
            }
        }
        other => panic!(
            "the encoding of a decoded {} decodes to {other:?}",
            message.kind_name()
        ),
    }
}

/// Checks the viewer stream's decoders on bytes: `decode_frame` with the server's and
/// the client's limits, and a [`FrameReader`] fed in chunks drawn from `seed`, takes
/// the same messages as decoding the whole buffer; every decoded message round-trips.
pub fn check_wire_bytes(data: &[u8], seed: u64) {
    for limits in [Limits::FROM_CLIENT, Limits::FROM_SERVER] {
        if let Ok(Some((message, used))) = wire::decode_frame(data, &limits) {
            assert!(
                used > wire::LENGTH_PREFIX && used <= data.len(),
                "consumed {used} of {}",
                data.len()
            );
            check_round_trip(&message, &limits);
        }
    }
    // The messages in the whole buffer, one after the other.
    let mut whole = Vec::new();
    let mut at = 0;
    while let Ok(Some((message, used))) = wire::decode_frame(&data[at..], &Limits::FROM_SERVER) {
        whole.push(message);
        at += used;
    }
    let mut rng = Rng::new(seed);
    let mut reader = FrameReader::default();
    let mut taken = Vec::new();
    let mut rest = data;
    'feed: while !rest.is_empty() {
        let n = 1 + rng.below(rest.len().min(256) as u64) as usize;
        let (chunk, later) = rest.split_at(n.min(rest.len()));
        rest = later;
        reader.buf.extend_from_slice(chunk);
        loop {
            match reader.take_message() {
                Ok(Some(m)) => {
                    check_round_trip(&m, &Limits::FROM_SERVER);
                    taken.push(m);
                }
                Ok(None) => break,
                Err(_) => break 'feed,
            }
        }
    }
    let encoded = |ms: &[Message]| ms.iter().map(|m| m.encode().ok()).collect::<Vec<_>>();
    assert_eq!(
        encoded(&taken),
        encoded(&whole),
        "chunked reads take the same messages"
    );
}

/// The `wire_decoder` fuzz target: the first byte picks raw bytes or a mutated
/// encoding of a sample message (the next bytes: which, then offset/xor pairs).
pub fn check_wire(data: &[u8]) {
    let mut s = Script(data);
    let mode = s.byte();
    let seed = u64::from(s.u16());
    if mode & 1 == 0 {
        check_wire_bytes(s.0, seed);
        return;
    }
    let messages = sample_messages();
    let pick = usize::from(s.byte()) % messages.len();
    let Ok(mut bytes) = messages[pick].encode() else {
        panic!("sample {pick} encodes");
    };
    while s.0.len() >= 3 {
        let at = usize::from(s.u16()) % bytes.len();
        bytes[at] ^= s.byte();
    }
    if mode & 2 != 0 {
        bytes.truncate(usize::from(seed as u8) % (bytes.len() + 1));
    }
    check_wire_bytes(&bytes, seed);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_reference_matches_the_decoder_counters_on_a_known_stream() {
        let stream = stream_of(&[
            Piece::Noise(b"noise TX".to_vec()),
            Piece::Valid {
                width: 5,
                height: 3,
                intensity: false,
                seq: 10,
            },
            Piece::CorruptCrc {
                width: 5,
                height: 3,
                seq: 11,
                at: 12,
                xor: 0xFF,
            },
            Piece::BadHeader { field: 0 },
            Piece::Valid {
                width: 5,
                height: 3,
                intensity: true,
                seq: 14,
            },
        ]);
        let r = reference_decode(&stream);
        assert_eq!(r.frames.iter().map(|f| f.seq).collect::<Vec<_>>(), [10, 14]);
        assert_eq!(r.counters.crc_errors, 1);
        assert_eq!(r.counters.bad_headers, 1);
        assert_eq!(r.counters.lost_frames, 3);
        assert_eq!(check_txl1_stream(&stream, 1), r);
    }

    /// The fuzz targets' bodies on seeded inputs, for CI without nightly: random bytes,
    /// random scripts, and mutations of both.
    #[test]
    fn seeded_txl1_inputs_pass_the_fuzz_checks() {
        let mut rng = Rng::new(0x7458_4C31);
        for _ in 0..10_000 {
            let len = rng.below(160) as usize;
            let mut data: Vec<u8> = (0..len).map(|_| rng.next_u64() as u8).collect();
            if rng.below(3) == 0 {
                // Raw bytes dense with magic prefixes and headers.
                for b in data.iter_mut().skip(3) {
                    if rng.below(3) == 0 {
                        *b = MAGIC[rng.below(4) as usize];
                    }
                }
            }
            check_txl1(&data);
        }
    }

    #[test]
    fn a_pose_with_huge_quaternion_components_decodes_to_a_rotation() {
        // Components above about 1e154 overflowed the norm once and decoded to the
        // zero quaternion, which then failed to decode when re-encoded.
        let mut bytes = Message::PoseRevised {
            id: 1,
            world_from_scan: Pose::identity(),
        }
        .encode()
        .unwrap_or_default();
        let q_at = bytes.len() - 4 * 8;
        for i in 0..4 {
            bytes[q_at + 8 * i..q_at + 8 * i + 8].copy_from_slice(&1e200f64.to_le_bytes());
        }
        let decoded = wire::decode_frame(&bytes, &Limits::FROM_SERVER);
        let Ok(Some((message, _))) = decoded else {
            panic!("decodes: {decoded:?}");
        };
        for p in poses(&message) {
            assert!((p.rotation.quaternion().norm() - 1.0).abs() < 1e-12);
            // Equal components: a third of a turn about (1, 1, 1) / sqrt(3), w = 0.5.
            assert!((p.rotation.quaternion().w - 0.5).abs() < 1e-12);
        }
        check_round_trip(&message, &Limits::FROM_SERVER);
    }

    #[test]
    fn seeded_wire_inputs_pass_the_fuzz_checks() {
        let mut rng = Rng::new(0x5458_4C56);
        for _ in 0..10_000 {
            let len = rng.below(96) as usize;
            let data: Vec<u8> = (0..len).map(|_| rng.next_u64() as u8).collect();
            check_wire(&data);
        }
        // Every sample, whole and in every truncation.
        for m in sample_messages() {
            let Ok(bytes) = m.encode() else {
                panic!("sample {} encodes", m.kind_name());
            };
            for cut in 0..=bytes.len() {
                check_wire_bytes(&bytes[..cut], cut as u64);
            }
        }
    }
}
