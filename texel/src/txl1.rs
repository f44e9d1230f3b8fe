//! The TXL1 serial lidar protocol: frame encoding for the simulator's virtual device
//! (`docs/simulator.md`), and a streaming decoder for the daemon's serial source
//! (`docs/daemon.md`) that resynchronises on the magic, tells "incomplete, read more"
//! from "invalid", counts every byte and frame it could not use, and does work linear
//! in the bytes it is given whatever they contain, in slices of bounded work.
//!
//! Neither page gives the byte layout, so this module is where it is written down.
//! All fields are little-endian. A frame is a [`HEADER_LEN`]-byte header: the magic
//! `TXL1`, version `u8` (1), flags `u8` (bit 0: an intensity block follows; other bits
//! 0), width and height `u16` (1 to [`MAX_SIDE`]), reserved `u16` (0), seq `u32`,
//! timestamp `u64` (ns), range unit `u32` (micrometres per count, > 0); then width x
//! height `u16` range counts, row-major ([`NO_RETURN`], [`INVALID`]), as many `u16`
//! intensities when flagged; then the CRC-32 (IEEE) of every byte after the magic,
//! `u32`.

use std::collections::VecDeque;

use memchr::memmem;

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
pub(crate) enum HeaderCheck {
    /// Not enough bytes yet.
    Incomplete,
    Invalid,
    /// The frame's total length in bytes.
    Valid(usize),
}

pub(crate) fn header_check(buf: &[u8]) -> HeaderCheck {
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

/// Counts the sequence gap between consecutive valid frames.
pub(crate) fn note_seq(counters: &mut Txl1Counters, last_seq: &mut Option<u32>, seq: u32) {
    counters.frames += 1;
    if let Some(last) = *last_seq {
        let gap = seq.wrapping_sub(last.wrapping_add(1));
        if gap < 1 << 31 {
            counters.lost_frames += u64::from(gap);
        } else {
            counters.seq_restarts += 1;
        }
    }
    *last_seq = Some(seq);
}

/// The decoder's work is linear in the bytes pushed: [`Txl1Decoder::work_units`] never
/// exceeds this many units per byte pushed, whatever the bytes are (the derivation is
/// on `work_units`; the property tests and the fuzz targets check it).
pub const WORK_UNITS_PER_BYTE: u64 = 40;

/// The stream's running CRC is recorded every this many bytes, so that the CRC of any
/// span costs at most twice this many bytes of hashing plus a constant.
const CHECKPOINT_EVERY: usize = 64;
/// The magic is searched for in windows of at most this many bytes, so that a call
/// with a work budget returns soon after spending it.
const SEARCH_WINDOW: usize = 64 * 1024;
/// Work units for one header check (the bytes it reads after the magic).
const HEADER_WORK: u64 = (HEADER_LEN - MAGIC.len()) as u64;
/// Work units for one multiplication in GF(2)[x] modulo the CRC polynomial (a
/// 32-step shift-and-xor loop).
const GF2_MUL_WORK: u64 = 32;

/// The CRC-32 polynomial, bit-reflected as the IEEE CRC computes it.
const CRC_POLY: u32 = 0xEDB8_8320;

/// `a * b` modulo the CRC polynomial, both bit-reflected (bit 31 is x^0), as zlib's
/// `multmodp`.
const fn gf2_mul(a: u32, mut b: u32) -> u32 {
    let mut product = 0;
    let mut bit = 1u32 << 31;
    while bit != 0 {
        if a & bit != 0 {
            product ^= b;
        }
        b = if b & 1 != 0 {
            (b >> 1) ^ CRC_POLY
        } else {
            b >> 1
        };
        bit >>= 1;
    }
    product
}

/// `X8N[k][d]` = x^(8 * d * 16^k) modulo the CRC polynomial: the factor that appends
/// `d * 16^k` zero bytes to a CRC, one table row per hex digit of a length.
const X8N: [[u32; 16]; 16] = {
    let mut table = [[0u32; 16]; 16];
    let mut step = 1u32 << 23; // x^8: one zero byte
    let mut k = 0;
    while k < 16 {
        table[k][0] = 1 << 31; // x^0
        let mut d = 1;
        while d < 16 {
            table[k][d] = gf2_mul(table[k][d - 1], step);
            d += 1;
        }
        step = gf2_mul(table[k][15], step);
        k += 1;
    }
    table
};

/// `crc * x^(8 * len)`: what the CRC of bytes A becomes in the CRC of A followed by
/// `len` bytes, less the CRC of those bytes alone. With it, CRC(B) = CRC(A ++ B) xor
/// `crc_shift(CRC(A), |B|)`, so the CRC of any span follows from two prefix CRCs.
/// Returns the multiplications done.
fn crc_shift(crc: u32, len: u64) -> (u32, u64) {
    let mut out = crc;
    let mut rest = len;
    let mut muls = 0;
    for row in &X8N {
        if rest == 0 {
            break;
        }
        let digit = (rest & 15) as usize;
        if digit != 0 {
            out = gf2_mul(row[digit], out);
            muls += 1;
        }
        rest >>= 4;
    }
    (out, muls)
}

fn crc_continue(crc: u32, bytes: &[u8]) -> u32 {
    let mut h = crc32fast::Hasher::new_with_initial(crc);
    h.update(bytes);
    h.finalize()
}

/// What [`Txl1Decoder::decode`] found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Txl1Step {
    /// A complete, valid frame.
    Frame(Txl1Frame),
    /// Incomplete: everything buffered is decided but for a frame (or header, or a
    /// possible magic) that needs more bytes. Push more.
    NeedBytes,
    /// The work budget of the call is spent; call again (after letting others run).
    Paused,
}

/// A streaming TXL1 decoder: feed it bytes as they arrive, take frames out.
///
/// Its work is linear in the bytes pushed whatever they contain. The bytes are read
/// through an offset (no shift of the rest per false start); the magic is searched
/// with `memchr::memmem`, each byte once, resuming where the last search stopped; a
/// header whose claimed frame is not yet buffered is checked once and then waits
/// without rescans; and a CRC is checked only once the whole claimed frame is
/// buffered, from CRCs of stream prefixes recorded as the bytes arrive, so that
/// headers nested inside one another's claimed spans (a false frame's span is
/// searched again for a real frame, from the byte after its magic) cost a constant
/// each instead of their span.
#[derive(Debug)]
pub struct Txl1Decoder {
    /// Received bytes; `buf[pos..]` are not consumed yet. The consumed front is
    /// reclaimed on a push once it is at least as long as the rest (so each byte is
    /// moved at most once on average), keeping the bytes since the last checkpoint.
    buf: Vec<u8>,
    pos: usize,
    /// Stream offset of `buf[0]`, a multiple of [`CHECKPOINT_EVERY`].
    base: u64,
    /// CRC-32 of every byte pushed so far.
    crc_all: u32,
    /// `checkpoints[i]`: CRC-32 of the stream's first `base + i * CHECKPOINT_EVERY`
    /// bytes.
    checkpoints: VecDeque<u32>,
    /// The header at `pos` is valid and claims a frame of this many bytes.
    pending: Option<usize>,
    /// Consumed bytes before this stream offset belong to a frame dropped for its CRC.
    bad_until: u64,
    /// Bytes were pushed since `decode` last answered `NeedBytes`.
    fresh: bool,
    finder: memmem::Finder<'static>,
    counters: Txl1Counters,
    last_seq: Option<u32>,
    work: u64,
}

impl Default for Txl1Decoder {
    fn default() -> Self {
        Self {
            buf: Vec::new(),
            pos: 0,
            base: 0,
            crc_all: 0,
            checkpoints: VecDeque::from([0]),
            pending: None,
            bad_until: 0,
            fresh: false,
            finder: memmem::Finder::new(&MAGIC).into_owned(),
            counters: Txl1Counters::default(),
            last_seq: None,
            work: 0,
        }
    }
}

impl Txl1Decoder {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn counters(&self) -> Txl1Counters {
        self.counters
    }

    /// Bytes held waiting for the rest of a frame (bounded by [`MAX_FRAME_LEN`] plus
    /// the last push once `decode` has answered `NeedBytes`; the allocation is at most
    /// about twice that).
    pub fn buffered(&self) -> usize {
        self.buf.len() - self.pos
    }

    /// The work done so far, in units of about one byte hashed, searched, read or
    /// copied (a GF(2) multiplication counts 32). Per byte pushed: 1 to hash it, 1 to
    /// search it, at most 1 to move it and 1 to decode it; per magic (4 bytes apart
    /// at least) a header check of 24 and a few bytes searched again; per header that
    /// passes its check (12 bytes apart at least, as nested valid headers cannot be
    /// closer) a CRC of at most 2 x 63 bytes hashed and 6 multiplications. That is
    /// under [`WORK_UNITS_PER_BYTE`] per byte pushed, whatever the bytes.
    pub fn work_units(&self) -> u64 {
        self.work
    }

    /// Appends received bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        if bytes.is_empty() {
            return;
        }
        self.reclaim();
        self.buf.extend_from_slice(bytes);
        let mut at = self.base + (self.buf.len() - bytes.len()) as u64;
        let mut rest = bytes;
        while !rest.is_empty() {
            let to_checkpoint = CHECKPOINT_EVERY - (at % CHECKPOINT_EVERY as u64) as usize;
            let (now, later) = rest.split_at(to_checkpoint.min(rest.len()));
            self.crc_all = crc_continue(self.crc_all, now);
            at += now.len() as u64;
            if at.is_multiple_of(CHECKPOINT_EVERY as u64) {
                self.checkpoints.push_back(self.crc_all);
            }
            rest = later;
        }
        self.work += bytes.len() as u64;
        self.fresh = true;
    }

    /// Drops the consumed front (from the checkpoint at or before `pos`) once it is at
    /// least as long as what would be kept.
    fn reclaim(&mut self) {
        let drop = self.pos - self.pos % CHECKPOINT_EVERY;
        if drop == 0 || drop < self.buf.len() - drop {
            return;
        }
        self.buf.drain(..drop);
        self.work += self.buf.len() as u64;
        self.pos -= drop;
        self.base += drop as u64;
        self.checkpoints.drain(..drop / CHECKPOINT_EVERY);
    }

    /// CRC-32 of the stream's bytes before `buf[at]`.
    fn crc_prefix(&mut self, at: usize) -> Option<u32> {
        let from = at - at % CHECKPOINT_EVERY;
        let checkpoint = *self.checkpoints.get(from / CHECKPOINT_EVERY)?;
        let bytes = self.buf.get(from..at)?;
        self.work += bytes.len() as u64;
        Some(crc_continue(checkpoint, bytes))
    }

    /// CRC-32 of `buf[start..end]`.
    fn crc_of(&mut self, start: usize, end: usize) -> u32 {
        match (self.crc_prefix(start), self.crc_prefix(end)) {
            (Some(before), Some(through)) => {
                let (shifted, muls) = crc_shift(before, (end - start) as u64);
                self.work += muls * GF2_MUL_WORK;
                through ^ shifted
            }
            // Unreachable while the checkpoint invariant holds; hashing the span is
            // slower but never wrong.
            _ => {
                self.work += (end - start) as u64;
                crc32fast::hash(self.buf.get(start..end).unwrap_or_default())
            }
        }
    }

    /// Consumes `n` bytes as not part of any valid frame, counting them.
    fn skip(&mut self, n: usize) {
        let n = n.min(self.buffered());
        let at = self.base + self.pos as u64;
        let bad = self.bad_until.saturating_sub(at).min(n as u64);
        self.counters.bytes_in_bad_frames += bad;
        self.counters.bytes_skipped += n as u64 - bad;
        self.pos += n;
        self.pending = None;
    }

    /// The next complete, valid frame in the buffer, or `None` when more bytes are
    /// needed. Everything before it that is not a valid frame is skipped and counted.
    pub fn next_frame(&mut self) -> Option<Txl1Frame> {
        loop {
            match self.decode(u64::MAX) {
                Txl1Step::Frame(frame) => return Some(frame),
                Txl1Step::NeedBytes => return None,
                Txl1Step::Paused => {}
            }
        }
    }

    /// Decodes until a frame is found, more bytes are needed, or about `max_work`
    /// work units are spent (a single step, such as decoding one large valid frame,
    /// may exceed it). A call with nothing pushed since `NeedBytes` does no work.
    pub fn decode(&mut self, max_work: u64) -> Txl1Step {
        if !self.fresh {
            return Txl1Step::NeedBytes;
        }
        let start = self.work;
        loop {
            if self.work - start >= max_work.max(1) {
                return Txl1Step::Paused;
            }
            if let Some(total) = self.pending {
                // 3. The claimed frame is whole: check its CRC once.
                if self.buffered() < total {
                    self.fresh = false;
                    return Txl1Step::NeedBytes;
                }
                if let Some(frame) = self.take_checked(total) {
                    return Txl1Step::Frame(frame);
                }
                continue;
            }
            // 1. Resynchronise on the magic, one window at a time.
            let end = self.buf.len().min(self.pos + SEARCH_WINDOW);
            let window = &self.buf[self.pos..end];
            match self.finder.find(window) {
                Some(p) => {
                    self.work += (p + MAGIC.len()) as u64;
                    self.skip(p);
                    // A magic ends the span of a frame dropped for its CRC.
                    self.bad_until = self.bad_until.min(self.base + self.pos as u64);
                }
                None if end < self.buf.len() => {
                    // Keep the last bytes: a magic may straddle the window's end.
                    let searched = window.len();
                    self.work += searched as u64;
                    self.skip(searched - (MAGIC.len() - 1));
                    continue;
                }
                None => {
                    // Keep a tail that could be the start of a magic split across
                    // reads.
                    let searched = window.len();
                    let keep = (1..MAGIC.len())
                        .rev()
                        .find(|&k| window.ends_with(&MAGIC[..k]))
                        .unwrap_or(0);
                    self.work += searched as u64;
                    self.skip(searched - keep);
                    self.fresh = false;
                    return Txl1Step::NeedBytes;
                }
            }
            // 2. Check the header without waiting for the payload it claims.
            match header_check(&self.buf[self.pos..]) {
                HeaderCheck::Incomplete => {
                    self.fresh = false;
                    return Txl1Step::NeedBytes;
                }
                HeaderCheck::Invalid => {
                    self.work += HEADER_WORK;
                    self.counters.bad_headers += 1;
                    self.skip(1);
                }
                HeaderCheck::Valid(total) => {
                    self.work += HEADER_WORK;
                    self.pending = Some(total);
                }
            }
        }
    }

    /// Checks the CRC of the whole frame of `total` bytes at `pos`; takes it if it
    /// holds, else drops its magic and marks its span as a bad frame's (the search
    /// resumes at the byte after the magic: the header may have been damaged, and a
    /// real frame may start inside the claimed span).
    fn take_checked(&mut self, total: usize) -> Option<Txl1Frame> {
        let crc_at = self.pos + total - CRC_LEN;
        let stored = self
            .buf
            .get(crc_at..crc_at + CRC_LEN)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]));
        let computed = self.crc_of(self.pos + MAGIC.len(), crc_at);
        if stored != Some(computed) {
            self.counters.crc_errors += 1;
            self.bad_until = self.base + (self.pos + total) as u64;
            self.skip(MAGIC.len());
            return None;
        }
        let frame = decode_valid(&self.buf[self.pos..self.pos + total]);
        self.work += total as u64;
        self.pos += total;
        self.pending = None;
        note_seq(&mut self.counters, &mut self.last_seq, frame.seq);
        Some(frame)
    }
}

/// Decodes a frame whose header and CRC were checked.
pub(crate) fn decode_valid(bytes: &[u8]) -> Txl1Frame {
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
    fn span_crcs_from_prefix_crcs_equal_the_crc_of_the_span() {
        let bytes: Vec<u8> = (0..5000u32).map(|i| (i * 7919 % 251) as u8).collect();
        for (a, b) in [
            (0, 0),
            (0, 1),
            (3, 64),
            (63, 65),
            (100, 4999),
            (0, 5000),
            (777, 778),
        ] {
            let whole = crc32fast::hash(&bytes[..b]);
            let (shifted, _) = crc_shift(crc32fast::hash(&bytes[..a]), (b - a) as u64);
            assert_eq!(whole ^ shifted, crc32fast::hash(&bytes[a..b]), "{a}..{b}");
        }
        assert_eq!(
            crc_continue(crc32fast::hash(&bytes[..10]), &bytes[10..99]),
            crc32fast::hash(&bytes[..99])
        );
    }

    /// The stream from the issue: a header claiming the largest legal frame, its span
    /// (CRC field included) filled with the magic, so the CRC fails and every one of
    /// the million false magics inside is a bad header; valid frames follow.
    fn false_magic_flood() -> (Vec<u8>, usize) {
        let mut stream = crate::fuzzing::header(MAX_SIDE, MAX_SIDE, true);
        assert_eq!(header_check(&stream), HeaderCheck::Valid(MAX_FRAME_LEN));
        let magics = (MAX_FRAME_LEN - HEADER_LEN) / MAGIC.len();
        stream.extend(MAGIC.repeat(magics));
        assert_eq!(stream.len(), MAX_FRAME_LEN);
        (stream, magics)
    }

    fn decode_all(d: &mut Txl1Decoder, stream: &[u8], split: usize) -> Vec<Txl1Frame> {
        let mut got = Vec::new();
        for chunk in stream.chunks(split) {
            d.push(chunk);
            while let Some(f) = d.next_frame() {
                got.push(f);
            }
        }
        got
    }

    #[test]
    fn a_false_magic_flood_after_a_bogus_large_header_is_decoded_in_linear_work() {
        let (mut stream, magics) = false_magic_flood();
        let flood_len = stream.len();
        let frames: Vec<_> = (1..=20).map(|s| frame(s, s % 2 == 0)).collect();
        for f in &frames {
            stream.extend(f.encode());
        }
        let n = stream.len() as u64;
        for split in [4096, 64 * 1024, stream.len()] {
            let mut d = Txl1Decoder::new();
            assert_eq!(decode_all(&mut d, &stream, split), frames, "split {split}");
            let c = d.counters();
            assert_eq!(c.crc_errors, 1);
            assert_eq!(c.bad_headers, magics as u64);
            // The bogus frame's bytes up to the first false magic, then every false
            // magic skipped as a bad header.
            assert_eq!(c.bytes_in_bad_frames, HEADER_LEN as u64);
            assert_eq!(c.bytes_skipped, (flood_len - HEADER_LEN) as u64);
            assert_eq!(d.buffered(), 0);
            let work = d.work_units();
            println!(
                "split {split}: {n} bytes, {work} work units ({:.2} per byte)",
                work as f64 / n as f64
            );
            assert!(
                work <= WORK_UNITS_PER_BYTE * n,
                "{work} work units for {n} bytes"
            );
        }
    }

    #[test]
    fn nested_headers_claiming_the_largest_frame_are_checked_in_linear_work() {
        // A valid header every 12 bytes, each claiming the largest frame: each one's
        // claimed span holds the next, and each CRC fails. Hashing each span in full
        // would hash 4 MiB some 350 000 times.
        let count = MAX_FRAME_LEN / 12;
        let nested = crate::fuzzing::Piece::Nested {
            count,
            width: MAX_SIDE,
            height: MAX_SIDE,
            intensity: true,
        };
        let mut stream = nested.bytes();
        stream.resize(12 * count + MAX_FRAME_LEN, 0);
        let frames: Vec<_> = (1..=5).map(|s| frame(s, true)).collect();
        for f in &frames {
            stream.extend(f.encode());
        }
        let n = stream.len() as u64;
        for split in [1000, 64 * 1024] {
            let mut d = Txl1Decoder::new();
            assert_eq!(decode_all(&mut d, &stream, split), frames, "split {split}");
            assert_eq!(d.counters().crc_errors, count as u64, "every nested header");
            let work = d.work_units();
            println!(
                "split {split}: {n} bytes, {work} work units ({:.2} per byte)",
                work as f64 / n as f64
            );
            assert!(
                work <= WORK_UNITS_PER_BYTE * n,
                "{work} work units for {n} bytes"
            );
        }
    }

    #[test]
    fn a_header_waiting_for_its_frame_is_not_checked_again_on_each_read() {
        let mut d = Txl1Decoder::new();
        d.push(&crate::fuzzing::header(MAX_SIDE, MAX_SIDE, false));
        assert_eq!(d.decode(u64::MAX), Txl1Step::NeedBytes);
        let before = d.work_units();
        for _ in 0..10_000 {
            d.push(&[0]);
            assert_eq!(d.decode(u64::MAX), Txl1Step::NeedBytes);
        }
        assert_eq!(
            d.work_units() - before,
            10_000,
            "one unit (its hash) per byte pushed"
        );
        assert_eq!(d.buffered(), HEADER_LEN + 10_000);
    }

    #[test]
    fn a_work_budget_pauses_decoding_and_resuming_loses_nothing() {
        let (mut stream, _) = false_magic_flood();
        stream.extend(frame(1, false).encode());
        let mut d = Txl1Decoder::new();
        d.push(&stream);
        let mut pauses = 0;
        let mut got = Vec::new();
        loop {
            let before = d.work_units();
            match d.decode(64 * 1024) {
                Txl1Step::Paused => pauses += 1,
                Txl1Step::Frame(f) => got.push(f),
                Txl1Step::NeedBytes => break,
            }
            assert!(
                d.work_units() - before < 64 * 1024 + 1024,
                "a call stops soon after its budget"
            );
        }
        assert_eq!(got, [frame(1, false)]);
        assert!(pauses > 100, "{pauses} pauses");
    }

    #[test]
    fn a_real_frame_hidden_in_a_bogus_span_is_found() {
        // A damaged header (width 6 instead of 5) claims 2 more bytes than the frame:
        // its CRC fails, and the next frame, inside the claimed span, is found.
        let mut bad = frame(1, false).encode();
        bad[6] = 6;
        let mut stream = bad.clone();
        stream.extend(frame(2, false).encode());
        stream.extend(frame(3, false).encode());
        for split in [1, 5, stream.len()] {
            let mut d = Txl1Decoder::new();
            let got: Vec<u32> = decode_all(&mut d, &stream, split)
                .iter()
                .map(|f| f.seq)
                .collect();
            assert_eq!(got, [2, 3], "split {split}");
            assert_eq!(d.counters().crc_errors, 1);
            assert_eq!(d.counters().bytes_in_bad_frames, bad.len() as u64);
        }
    }

    mod work {
        use super::*;
        use crate::fuzzing::{Piece, check_txl1_stream, stream_of};
        use proptest::prelude::*;

        fn side() -> impl Strategy<Value = u16> {
            prop_oneof![1u16..9, 1u16..=MAX_SIDE]
        }

        fn piece() -> impl Strategy<Value = Piece> {
            let small = (1u16..9, 1u16..9, any::<u32>());
            prop_oneof![
                (small.clone(), any::<bool>()).prop_map(|((width, height, seq), intensity)| {
                    Piece::Valid {
                        width,
                        height,
                        intensity,
                        seq,
                    }
                }),
                (small.clone(), any::<usize>(), any::<u8>()).prop_map(
                    |((width, height, seq), at, xor)| Piece::CorruptCrc {
                        width,
                        height,
                        seq,
                        at,
                        xor
                    }
                ),
                (small.clone(), any::<usize>(), any::<u8>()).prop_map(
                    |((width, height, seq), at, xor)| Piece::Damaged {
                        width,
                        height,
                        seq,
                        at,
                        xor
                    }
                ),
                (side(), side(), any::<bool>()).prop_map(|(width, height, intensity)| {
                    Piece::Claims {
                        width,
                        height,
                        intensity,
                    }
                }),
                (0usize..2048).prop_map(Piece::MagicFlood),
                any::<u8>().prop_map(|field| Piece::BadHeader { field }),
                (small.clone(), any::<usize>()).prop_map(|((width, height, seq), keep)| {
                    Piece::Truncated {
                        width,
                        height,
                        seq,
                        keep,
                    }
                }),
                (0usize..400, 1u16..40, 1u16..40, any::<bool>()).prop_map(
                    |(count, width, height, intensity)| Piece::Nested {
                        count,
                        width,
                        height,
                        intensity
                    }
                ),
                proptest::collection::vec(any::<u8>(), 0..64).prop_map(Piece::Noise),
            ]
        }

        proptest! {
            #![proptest_config(ProptestConfig::with_cases(256))]

            /// Any mix of magics, bad headers, headers claiming huge frames, corrupt
            /// and valid frames, in any chunking and with any work budget, costs at
            /// most `WORK_UNITS_PER_BYTE` per byte, and decodes as the plain
            /// whole-stream rules do.
            #[test]
            fn decoding_work_is_linear_in_the_bytes(
                pieces in proptest::collection::vec(piece(), 0..40),
                seed in any::<u64>(),
            ) {
                let stream = stream_of(&pieces);
                check_txl1_stream(&stream, seed);
            }
        }
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
