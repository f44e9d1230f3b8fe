//! The TXL1 serial lidar protocol: frame encoding for the simulator's virtual device
//! (`docs/simulator.md`), and a streaming decoder for the daemon's serial source
//! (`docs/daemon.md`) that resynchronises on the magic, tells "incomplete, read more"
//! from "invalid", and counts every byte and frame it could not use.
//!
//! Neither page gives the byte layout, so this module is where it is written down.
//! All fields are little-endian. A frame is a [`HEADER_LEN`]-byte header: the magic
//! `TXL1`, version `u8` (1), flags `u8` (bit 0: an intensity block follows; other bits
//! 0), width and height `u16` (1 to [`MAX_SIDE`]), reserved `u16` (0), seq `u32`,
//! timestamp `u64` (ns), range unit `u32` (micrometres per count, > 0); then width x
//! height `u16` range counts, row-major ([`NO_RETURN`], [`INVALID`]), as many `u16`
//! intensities when flagged; then the CRC-32 (IEEE) of every byte after the magic,
//! `u32`.

use crate::frames::RangeFrame;

pub const MAGIC: [u8; 4] = *b"TXL1";
pub const VERSION: u8 = 1;
pub const HEADER_LEN: usize = 28;
pub const CRC_LEN: usize = 4;
pub const MAX_SIDE: u16 = 1024;
/// Range counts with these values carry no range.
pub const NO_RETURN: u16 = 0;
pub const INVALID: u16 = 0xFFFF;
const FLAG_INTENSITY: u8 = 0x01;

/// The largest frame the protocol allows (1024x1024 with intensity): the decoder
/// never buffers more than this plus one read.
pub const MAX_FRAME_LEN: usize =
    HEADER_LEN + 2 * 2 * MAX_SIDE as usize * MAX_SIDE as usize + CRC_LEN;

/// One TXL1 frame as it travels on the wire.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Txl1Frame {
    pub width: u16,
    pub height: u16,
    pub seq: u32,
    pub timestamp_ns: u64,
    /// Micrometres per range count (1000 = millimetres).
    pub range_unit_um: u32,
    /// Row-major counts; 0 = no return, 0xFFFF = invalid.
    pub ranges: Vec<u16>,
    pub intensities: Option<Vec<u16>>,
}

impl Txl1Frame {
    /// Quantises a range frame to counts of `range_unit_um` (ranges that do not fit
    /// are clamped to the largest valid count; no-returns become 0). Frames larger
    /// than the protocol allows are refused.
    pub fn from_range_frame(frame: &RangeFrame, range_unit_um: u32) -> Option<Self> {
        let width = u16::try_from(frame.width).ok()?;
        let height = u16::try_from(frame.height).ok()?;
        if width == 0 || height == 0 || width > MAX_SIDE || height > MAX_SIDE || range_unit_um == 0
        {
            return None;
        }
        if !frame.is_consistent() {
            return None;
        }
        let metres_per_count = f64::from(range_unit_um) * 1e-6;
        let ranges = frame
            .ranges_m
            .iter()
            .map(|&r| {
                if crate::frames::is_return(r) {
                    (f64::from(r) / metres_per_count)
                        .round()
                        .clamp(1.0, f64::from(INVALID - 1)) as u16
                } else {
                    NO_RETURN
                }
            })
            .collect();
        let intensities = frame.intensity.as_ref().map(|values| {
            values
                .iter()
                .map(|&v| {
                    if v.is_finite() {
                        v.round().clamp(0.0, 65535.0) as u16
                    } else {
                        0
                    }
                })
                .collect()
        });
        Some(Self {
            width,
            height,
            seq: frame.seq,
            timestamp_ns: frame.timestamp_ns,
            range_unit_um,
            ranges,
            intensities,
        })
    }

    /// The range frame this wire frame carries (ranges in metres, NaN for no-return
    /// and invalid counts).
    pub fn to_range_frame(&self) -> RangeFrame {
        let metres_per_count = f64::from(self.range_unit_um) * 1e-6;
        RangeFrame {
            width: u32::from(self.width),
            height: u32::from(self.height),
            ranges_m: self
                .ranges
                .iter()
                .map(|&c| match c {
                    NO_RETURN | INVALID => f32::NAN,
                    c => (f64::from(c) * metres_per_count) as f32,
                })
                .collect(),
            timestamp_ns: self.timestamp_ns,
            seq: self.seq,
            intensity: self
                .intensities
                .as_ref()
                .map(|v| v.iter().map(|&i| f32::from(i)).collect()),
        }
    }

    /// The frame's bytes on the wire.
    pub fn encode(&self) -> Vec<u8> {
        let pixels = usize::from(self.width) * usize::from(self.height);
        let blocks = if self.intensities.is_some() { 2 } else { 1 };
        let mut out = Vec::with_capacity(HEADER_LEN + 2 * pixels * blocks + CRC_LEN);
        out.extend_from_slice(&MAGIC);
        out.push(VERSION);
        out.push(if self.intensities.is_some() {
            FLAG_INTENSITY
        } else {
            0
        });
        out.extend_from_slice(&self.width.to_le_bytes());
        out.extend_from_slice(&self.height.to_le_bytes());
        out.extend_from_slice(&0u16.to_le_bytes());
        out.extend_from_slice(&self.seq.to_le_bytes());
        out.extend_from_slice(&self.timestamp_ns.to_le_bytes());
        out.extend_from_slice(&self.range_unit_um.to_le_bytes());
        for r in self.ranges.iter().take(pixels) {
            out.extend_from_slice(&r.to_le_bytes());
        }
        if let Some(intensities) = &self.intensities {
            for i in intensities.iter().take(pixels) {
                out.extend_from_slice(&i.to_le_bytes());
            }
        }
        let crc = crc32fast::hash(&out[MAGIC.len()..]);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }
}

/// What the decoder could not use, for the daemon's status.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Txl1Counters {
    /// Frames decoded with a valid CRC.
    pub frames: u64,
    /// Bytes outside any frame (line noise, partial frames at start-up).
    pub bytes_skipped: u64,
    /// Headers refused at once (bad version, size, reserved field, flags or unit).
    pub bad_headers: u64,
    /// Frames dropped for a CRC mismatch.
    pub crc_errors: u64,
    /// Bytes of the frames dropped for a CRC mismatch.
    pub bytes_in_bad_frames: u64,
    /// Sequence numbers missing between consecutive valid frames (frames the device
    /// sent that never arrived intact, CRC-dropped ones included).
    pub lost_frames: u64,
    /// Times the sequence went backwards (a device restart): not counted as loss.
    pub seq_restarts: u64,
}

/// Why a header was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum HeaderCheck {
    /// Not enough bytes yet.
    Incomplete,
    Invalid,
    /// The frame's total length in bytes.
    Valid(usize),
}

fn header_check(buf: &[u8]) -> HeaderCheck {
    if buf.len() < HEADER_LEN {
        return HeaderCheck::Incomplete;
    }
    let u16_at = |o: usize| u16::from_le_bytes([buf[o], buf[o + 1]]);
    let version = buf[4];
    let flags = buf[5];
    let width = u16_at(6);
    let height = u16_at(8);
    let reserved = u16_at(10);
    let unit = u32::from_le_bytes([buf[24], buf[25], buf[26], buf[27]]);
    let ok = version == VERSION
        && flags & !FLAG_INTENSITY == 0
        && (1..=MAX_SIDE).contains(&width)
        && (1..=MAX_SIDE).contains(&height)
        && reserved == 0
        && unit > 0;
    if !ok {
        return HeaderCheck::Invalid;
    }
    let blocks = if flags & FLAG_INTENSITY != 0 { 2 } else { 1 };
    HeaderCheck::Valid(HEADER_LEN + 2 * usize::from(width) * usize::from(height) * blocks + CRC_LEN)
}

/// A streaming TXL1 decoder: feed it bytes as they arrive, take frames out.
#[derive(Debug, Default)]
pub struct Txl1Decoder {
    buf: Vec<u8>,
    counters: Txl1Counters,
    last_seq: Option<u32>,
}

impl Txl1Decoder {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn counters(&self) -> Txl1Counters {
        self.counters
    }

    /// Bytes held waiting for the rest of a frame (bounded by [`MAX_FRAME_LEN`] plus
    /// the last push).
    pub fn buffered(&self) -> usize {
        self.buf.len()
    }

    /// Appends received bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
    }

    /// Skips `n` bytes as not part of any frame.
    fn skip(&mut self, n: usize) {
        let n = n.min(self.buf.len());
        self.buf.drain(..n);
        self.counters.bytes_skipped += n as u64;
    }

    fn find_magic(buf: &[u8], from: usize) -> Option<usize> {
        buf.get(from..)?
            .windows(MAGIC.len())
            .position(|w| w == MAGIC)
            .map(|p| p + from)
    }

    /// The next complete, valid frame in the buffer, or `None` when more bytes are
    /// needed. Everything before it that is not a valid frame is skipped and counted.
    pub fn next_frame(&mut self) -> Option<Txl1Frame> {
        loop {
            // 1. Resynchronise on the magic. Keep a tail that could be the start of
            //    a magic split across reads.
            match Self::find_magic(&self.buf, 0) {
                Some(0) => {}
                Some(p) => self.skip(p),
                None => {
                    let keep = (MAGIC.len() - 1).min(self.buf.len());
                    let tail_is_prefix = (1..=keep)
                        .rev()
                        .find(|&k| self.buf[self.buf.len() - k..] == MAGIC[..k]);
                    let keep = tail_is_prefix.unwrap_or(0);
                    self.skip(self.buf.len() - keep);
                    return None;
                }
            }
            // 2. Check the header without waiting for the payload it claims.
            let total = match header_check(&self.buf) {
                HeaderCheck::Incomplete => return None,
                HeaderCheck::Invalid => {
                    self.counters.bad_headers += 1;
                    self.skip(1);
                    continue;
                }
                HeaderCheck::Valid(total) => total,
            };
            if self.buf.len() < total {
                return None;
            }
            // 3. Check the CRC over everything after the magic.
            let crc_at = total - CRC_LEN;
            let crc = u32::from_le_bytes([
                self.buf[crc_at],
                self.buf[crc_at + 1],
                self.buf[crc_at + 2],
                self.buf[crc_at + 3],
            ]);
            if crc32fast::hash(&self.buf[MAGIC.len()..crc_at]) != crc {
                self.counters.crc_errors += 1;
                // If the header itself was damaged the frame may be shorter than it
                // claims: resume at the next magic inside the claimed span.
                let end = Self::find_magic(&self.buf[..total], MAGIC.len()).unwrap_or(total);
                self.buf.drain(..end);
                self.counters.bytes_in_bad_frames += end as u64;
                continue;
            }
            // 4. Decode.
            let frame = decode_valid(&self.buf[..total]);
            self.buf.drain(..total);
            self.counters.frames += 1;
            if let Some(last) = self.last_seq {
                let gap = frame.seq.wrapping_sub(last.wrapping_add(1));
                if gap < 1 << 31 {
                    self.counters.lost_frames += u64::from(gap);
                } else {
                    self.counters.seq_restarts += 1;
                }
            }
            self.last_seq = Some(frame.seq);
            return Some(frame);
        }
    }
}

/// Decodes a frame whose header and CRC were checked.
fn decode_valid(bytes: &[u8]) -> Txl1Frame {
    let u16_at = |o: usize| u16::from_le_bytes([bytes[o], bytes[o + 1]]);
    let width = u16_at(6);
    let height = u16_at(8);
    let pixels = usize::from(width) * usize::from(height);
    let block = |start: usize| -> Vec<u16> {
        bytes[start..start + 2 * pixels]
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect()
    };
    let mut timestamp = [0u8; 8];
    timestamp.copy_from_slice(&bytes[16..24]);
    Txl1Frame {
        width,
        height,
        seq: u32::from_le_bytes([bytes[12], bytes[13], bytes[14], bytes[15]]),
        timestamp_ns: u64::from_le_bytes(timestamp),
        range_unit_um: u32::from_le_bytes([bytes[24], bytes[25], bytes[26], bytes[27]]),
        ranges: block(HEADER_LEN),
        intensities: (bytes[5] & FLAG_INTENSITY != 0).then(|| block(HEADER_LEN + 2 * pixels)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(seq: u32, intensity: bool) -> Txl1Frame {
        Txl1Frame {
            width: 5,
            height: 3,
            seq,
            timestamp_ns: 1_000_000 * u64::from(seq),
            range_unit_um: 250,
            ranges: (0..15)
                .map(|i| if i == 4 { 0 } else { 1000 + i * 3 })
                .collect(),
            intensities: intensity.then(|| (0..15).map(|i| i * 100).collect()),
        }
    }

    #[test]
    fn frames_round_trip_through_bytes_in_any_split() {
        let frames = [frame(1, false), frame(2, true), frame(3, false)];
        let bytes: Vec<u8> = frames.iter().flat_map(Txl1Frame::encode).collect();
        for split in [1, 2, 3, 7, 64, bytes.len()] {
            let mut d = Txl1Decoder::new();
            let mut got = Vec::new();
            for chunk in bytes.chunks(split) {
                d.push(chunk);
                while let Some(f) = d.next_frame() {
                    got.push(f);
                }
            }
            assert_eq!(got, frames, "split {split}");
            assert_eq!(d.counters().bytes_skipped, 0);
            assert_eq!(d.counters().lost_frames, 0);
        }
    }

    #[test]
    fn garbage_crc_errors_and_gaps_are_counted_exactly() {
        let mut bytes = b"noise TX".to_vec(); // 8 garbage bytes, one looks like a magic start
        bytes.extend(frame(10, false).encode());
        let mut bad = frame(11, true).encode();
        bad[40] ^= 0xFF; // payload damage
        bytes.extend(&bad);
        bytes.extend(b"TXL1\x07garbage!"); // a bad header (version 7): 13 bytes
        bytes.extend(frame(14, false).encode()); // 12 and 13 never sent
        let mut d = Txl1Decoder::new();
        d.push(&bytes);
        let mut seqs = vec![];
        while let Some(f) = d.next_frame() {
            seqs.push(f.seq);
        }
        assert_eq!(seqs, [10, 14]);
        let c = d.counters();
        assert_eq!(c.frames, 2);
        assert_eq!(c.crc_errors, 1);
        assert_eq!(c.bytes_in_bad_frames, bad.len() as u64);
        assert_eq!(c.bad_headers, 1);
        assert_eq!(c.bytes_skipped, 8 + 13);
        assert_eq!(c.lost_frames, 3, "11 (CRC), 12 and 13");
    }

    #[test]
    fn oversize_headers_are_refused_without_waiting() {
        let mut h = frame(1, false).encode();
        h[6..8].copy_from_slice(&2000u16.to_le_bytes());
        let mut d = Txl1Decoder::new();
        d.push(&h[..HEADER_LEN]);
        assert!(d.next_frame().is_none());
        assert_eq!(d.counters().bad_headers, 1);
        assert!(
            d.buffered() < MAGIC.len(),
            "nothing waits for the claimed payload"
        );
    }

    #[test]
    fn range_frames_convert_both_ways() {
        let mut r = RangeFrame::empty(4, 2, 99, 7);
        r.ranges_m = vec![1.0, f32::NAN, 0.0, 12.345, 70.0, 0.0001, 3.5, 2.25];
        let w = Txl1Frame::from_range_frame(&r, 1000).unwrap();
        assert_eq!(w.ranges[..4], [1000, 0, 0, 12345]);
        assert_eq!(w.ranges[4], 65534, "clamped, never invalid");
        assert_eq!(w.ranges[5], 1, "a return never becomes no-return");
        let back = w.to_range_frame();
        assert_eq!(back.ranges_m[0], 1.0);
        assert!(back.ranges_m[1].is_nan() && back.ranges_m[2].is_nan());
        assert!((back.ranges_m[3] - 12.345).abs() < 1e-6);
        let mut w2 = w.clone();
        w2.ranges[0] = INVALID;
        assert!(w2.to_range_frame().ranges_m[0].is_nan());
        assert!(Txl1Frame::from_range_frame(&RangeFrame::empty(2000, 1, 0, 0), 1000).is_none());
    }

    #[test]
    fn sequence_wrap_is_not_loss_and_restart_is_counted() {
        let mut d = Txl1Decoder::new();
        for seq in [u32::MAX - 1, u32::MAX, 0, 1, 0] {
            d.push(&frame(seq, false).encode());
            assert!(d.next_frame().is_some());
        }
        assert_eq!(d.counters().lost_frames, 0);
        assert_eq!(d.counters().seq_restarts, 1);
    }
}
