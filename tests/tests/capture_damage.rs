//! The capture reader recovers around damage: a flipped byte costs only the chunk it
//! hit (named with its log times), damaged framing is scanned past, a recording cut
//! short still reads around damage before the cut, and a forged size is refused
//! without being allocated. Chunk positions and times come from the mcap crate's own
//! summary reader, an implementation independent of the project's.
#![allow(clippy::unwrap_used, clippy::expect_used)]
// tests panic on failure by design
// The counting allocator must implement `GlobalAlloc`, an unsafe trait; it only
// counts and forwards to the system allocator.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::io::Cursor;

use proptest::prelude::*;
use texel::capture::{
    CaptureError, CaptureEvent, CaptureReader, CaptureWriter, EoEncoding, RangeEncoding,
    WriterOptions,
};
use texel_e2e::captures;

/// Counts the bytes this thread holds, and the most it held, so a test can tell what
/// reading one file allocated whatever other tests do meanwhile.
struct CountingAlloc;

thread_local! {
    static HELD: Cell<usize> = const { Cell::new(0) };
    static PEAK: Cell<usize> = const { Cell::new(0) };
}

unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let _ = HELD.try_with(|h| {
            h.set(h.get() + layout.size());
            let _ = PEAK.try_with(|p| p.set(p.get().max(h.get())));
        });
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        let _ = HELD.try_with(|h| h.set(h.get().saturating_sub(layout.size())));
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static ALLOC: CountingAlloc = CountingAlloc;

const FRAMES: u32 = 40;
const PERIOD_NS: u64 = 50_000_000;

/// A capture of `FRAMES` frames in small chunks (about one frame each), and its
/// chunks as the mcap crate's summary reader lists them.
fn chunked_capture() -> (Vec<u8>, Vec<mcap::records::ChunkIndex>, u64) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("c.mcap");
    let options = WriterOptions {
        chunk_size_bytes: 8 << 10,
        ..WriterOptions::default()
    };
    let model = captures::sensor();
    let mut w = CaptureWriter::create(&path, options).unwrap();
    w.write_sensor(&model, captures::timestamp(0, PERIOD_NS))
        .unwrap();
    for i in 0..FRAMES {
        let t = captures::timestamp(i, PERIOD_NS);
        let (r, eo) = captures::frame(&model, i, t);
        w.write_range(&r, RangeEncoding::F32Metres).unwrap();
        w.write_eo(&eo, EoEncoding::Rgb8).unwrap();
    }
    w.finish().unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
    let footer = mcap::read::footer(&bytes).unwrap();
    let mut chunks = summary.chunk_indexes.clone();
    chunks.sort_by_key(|c| c.chunk_start_offset);
    assert!(chunks.len() >= 20, "{} chunks", chunks.len());
    (bytes, chunks, footer.summary_start)
}

struct Read {
    range_times: Vec<u64>,
    damaged: Vec<CaptureError>,
    spec_errors: Vec<CaptureError>,
    fatal: Option<CaptureError>,
}

/// Reads `bytes` as a file (with its summary, as `texeld` opens captures).
fn read(bytes: &[u8]) -> Read {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("damaged.mcap");
    std::fs::write(&path, bytes).unwrap();
    let mut out = Read {
        range_times: Vec::new(),
        damaged: Vec::new(),
        spec_errors: Vec::new(),
        fatal: None,
    };
    for item in CaptureReader::open(&path).unwrap() {
        match item {
            Ok(CaptureEvent::Range(f)) => out.range_times.push(f.timestamp_ns),
            Ok(_) => {}
            Err(e @ CaptureError::Damaged { .. }) => out.damaged.push(e),
            Err(e) if e.is_fatal() => {
                out.fatal = Some(e);
                break;
            }
            // Frames after a lost calibration break the reading rules: named, skipped.
            Err(e) => out.spec_errors.push(e),
        }
    }
    out
}

fn all_times() -> Vec<u64> {
    (0..FRAMES)
        .map(|i| captures::timestamp(i, PERIOD_NS))
        .collect()
}

/// The range frames whose messages lie in `chunk`.
fn times_in(chunk: &mcap::records::ChunkIndex) -> Vec<u64> {
    all_times()
        .into_iter()
        .filter(|t| (chunk.message_start_time..=chunk.message_end_time).contains(t))
        .collect()
}

#[test]
fn one_damaged_byte_costs_only_the_chunk_it_hit() {
    let (bytes, chunks, _) = chunked_capture();
    let mut frames_lost = 0;
    for chunk in &chunks[1..] {
        let mut damaged = bytes.clone();
        // A byte in the middle of the chunk's compressed records.
        let at = (chunk.chunk_start_offset + chunk.chunk_length / 2 + 20) as usize;
        damaged[at] ^= 0x5A;
        let got = read(&damaged);
        assert!(got.fatal.is_none(), "{:?}", got.fatal);
        assert!(got.spec_errors.is_empty(), "{:?}", got.spec_errors);
        let lost = times_in(chunk);
        frames_lost += lost.len();
        let expected: Vec<u64> = all_times()
            .into_iter()
            .filter(|t| !lost.contains(t))
            .collect();
        assert_eq!(got.range_times, expected, "byte {at} flipped");
        let [
            CaptureError::Damaged {
                offset,
                end,
                lost_log_time_ns,
                ..
            },
        ] = got.damaged.as_slice()
        else {
            panic!("byte {at}: {:?}", got.damaged);
        };
        assert_eq!(*offset, chunk.chunk_start_offset);
        assert_eq!(*end, chunk.chunk_start_offset + chunk.chunk_length);
        assert_eq!(
            *lost_log_time_ns,
            Some((chunk.message_start_time, chunk.message_end_time))
        );
        let text = got.damaged[0].to_string();
        assert!(
            text.contains(&format!(
                "{}..{}",
                chunk.message_start_time, chunk.message_end_time
            )),
            "{text}"
        );
    }
    assert!(frames_lost > 0, "some chunk held a range frame");
}

#[test]
fn damaged_framing_is_scanned_past() {
    let (bytes, chunks, _) = chunked_capture();
    let chunk = &chunks[chunks.len() / 2];
    let mut damaged = bytes.clone();
    // The top byte of the chunk's record length: it now claims far more than the file.
    damaged[chunk.chunk_start_offset as usize + 8] ^= 0x40;
    let got = read(&damaged);
    assert!(got.fatal.is_none(), "{:?}", got.fatal);
    let lost = times_in(chunk);
    let expected: Vec<u64> = all_times()
        .into_iter()
        .filter(|t| !lost.contains(t))
        .collect();
    assert_eq!(got.range_times, expected);
    assert_eq!(got.damaged.len(), 1, "{:?}", got.damaged);
    let CaptureError::Damaged {
        offset,
        end,
        lost_log_time_ns,
        ..
    } = &got.damaged[0]
    else {
        unreachable!()
    };
    // From the damaged record to the next chunk that checks out.
    assert_eq!(*offset, chunk.chunk_start_offset);
    let next = chunks
        .iter()
        .find(|c| c.chunk_start_offset > chunk.chunk_start_offset)
        .unwrap();
    assert!(*end <= next.chunk_start_offset, "{end}");
    assert_eq!(
        *lost_log_time_ns,
        Some((chunk.message_start_time, chunk.message_end_time))
    );
}

#[test]
fn a_recording_cut_short_reads_around_damage_then_says_it_is_truncated() {
    let (bytes, chunks, summary_start) = chunked_capture();
    // No summary, no footer: as a recorder killed mid-session leaves its file.
    let mut cut = bytes[..summary_start as usize].to_vec();
    let chunk = &chunks[5];
    let at = (chunk.chunk_start_offset + chunk.chunk_length / 2 + 20) as usize;
    cut[at] ^= 0xA5;
    let cut_len = cut.len() as u64;
    let mut range_times = Vec::new();
    let mut damaged = 0;
    let mut end = None;
    for item in CaptureReader::new(Cursor::new(cut), Some(cut_len), "cut".into()) {
        match item {
            Ok(CaptureEvent::Range(f)) => range_times.push(f.timestamp_ns),
            Ok(_) => {}
            Err(CaptureError::Damaged { .. }) => damaged += 1,
            Err(e) => {
                end = Some(e);
                break;
            }
        }
    }
    assert_eq!(damaged, 1);
    let lost = times_in(chunk);
    assert_eq!(range_times.len(), FRAMES as usize - lost.len());
    assert!(
        matches!(end, Some(CaptureError::Truncated { file_len, .. }) if file_len == cut_len),
        "{end:?}"
    );
}

#[test]
fn a_chunk_claiming_511_mib_is_refused_without_allocating_it() {
    let (bytes, chunks, _) = chunked_capture();
    let first = &chunks[1];
    let o = first.chunk_start_offset as usize;
    let claim: u64 = 511 << 20;
    for (what, edit) in [
        // The record's length: more than the file holds.
        ("record length", o + 1),
        // The uncompressed size in the chunk header: what a decompressor would be
        // asked to produce.
        ("uncompressed size", o + 9 + 16),
    ] {
        let mut forged = bytes.clone();
        forged[edit..edit + 8].copy_from_slice(&claim.to_le_bytes());
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("forged.mcap");
        std::fs::write(&path, &forged).unwrap();
        let held_before = HELD.with(Cell::get);
        PEAK.with(|p| p.set(held_before));
        let mut frames = 0;
        let mut damaged = 0;
        for item in CaptureReader::open(&path).unwrap() {
            match item {
                Ok(CaptureEvent::Range(_)) => frames += 1,
                Ok(_) => {}
                Err(CaptureError::Damaged { .. }) => damaged += 1,
                Err(e) => panic!("{what}: {e}"),
            }
        }
        let peak = PEAK.with(Cell::get) - held_before;
        assert!(
            peak < 16 << 20,
            "{what}: reading allocated up to {} MiB",
            peak >> 20
        );
        assert_eq!(damaged, 1, "{what}");
        assert_eq!(frames, FRAMES as usize - times_in(first).len(), "{what}");
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    /// Any 1 to 50 flipped bytes in the data section from the first chunk on: every
    /// chunk no flip touched is read whole (when the first chunk, which holds the
    /// calibration the frames need, is among them), the rest is reported, and nothing
    /// ends the read early. (A flip in the file's header record, before the first
    /// chunk, can cost the chunks up to where the reader finds its footing again; the
    /// test below only asks that such a read ends in an answer.)
    #[test]
    fn every_undamaged_chunk_is_read(seed in any::<u64>(), flips in 1usize..50) {
        let (bytes, chunks, summary_start) = shared_capture();
        let first = chunks[0].chunk_start_offset;
        let mut damaged = bytes.clone();
        let mut state = seed | 1;
        let mut hit = Vec::new();
        for _ in 0..flips {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let at = (first + state % (summary_start - first)) as usize;
            damaged[at] ^= ((state >> 40) as u8) | 1;
            hit.push(at as u64);
        }
        let got = read(&damaged);
        prop_assert!(got.fatal.is_none(), "{:?}", got.fatal);
        let untouched: Vec<_> = chunks
            .iter()
            .filter(|c| !hit.iter().any(|&h| {
                h >= c.chunk_start_offset && h < c.chunk_start_offset + c.chunk_length
            }))
            .collect();
        let calibration_read = untouched
            .first()
            .is_some_and(|c| c.chunk_start_offset == chunks[0].chunk_start_offset);
        for chunk in untouched.iter().filter(|_| calibration_read) {
            for t in times_in(chunk) {
                prop_assert!(got.range_times.contains(&t), "frame at {} lost", t);
            }
        }
        prop_assert!(!got.damaged.is_empty() || got.range_times.len() == FRAMES as usize);
    }

    /// Flips anywhere, the summary and footer included: the read ends, never panics.
    #[test]
    fn damage_anywhere_ends_in_an_answer(seed in any::<u64>(), flips in 1usize..50) {
        let (bytes, _, _) = shared_capture();
        let mut damaged = bytes.clone();
        let mut state = seed | 1;
        for _ in 0..flips {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let at = (state % bytes.len() as u64) as usize;
            damaged[at] ^= ((state >> 40) as u8) | 1;
        }
        let got = read(&damaged);
        prop_assert!(got.range_times.len() <= FRAMES as usize);
    }
}

/// One capture for every proptest case.
fn shared_capture() -> &'static (Vec<u8>, Vec<mcap::records::ChunkIndex>, u64) {
    static CAPTURE: std::sync::OnceLock<(Vec<u8>, Vec<mcap::records::ChunkIndex>, u64)> =
        std::sync::OnceLock::new();
    CAPTURE.get_or_init(chunked_capture)
}

/// What every input must give, whatever its bytes: an answer (events, then at most one
/// fatal error, which is the last item), in bounded work, with no panic. The fuzz
/// target `capture_reader` runs the same check under libFuzzer.
fn read_anything(bytes: &[u8]) -> usize {
    let mut items = 0;
    let mut ended = false;
    for item in CaptureReader::new(Cursor::new(bytes), Some(bytes.len() as u64), "x".into()) {
        assert!(!ended, "an item after a fatal error");
        items += 1;
        if let Err(e) = item {
            ended = e.is_fatal();
            // Every error names the file.
            assert!(e.to_string().starts_with("x:"), "{e}");
        }
        assert!(items <= bytes.len() + 1, "more items than bytes");
    }
    items
}

#[test]
fn mutated_captures_and_random_bytes_always_get_an_answer() {
    let (bytes, _, _) = shared_capture();
    let mut state: u64 = 0x2545_F491_4F6C_DD1D;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let mut answered = 0;
    for case in 0..2_000u32 {
        let mut input = bytes.clone();
        match case % 4 {
            // Flips.
            0 => {
                for _ in 0..1 + next() % 16 {
                    let at = (next() % input.len() as u64) as usize;
                    input[at] ^= (next() as u8) | 1;
                }
            }
            // A cut.
            1 => input.truncate((next() % input.len() as u64) as usize),
            // A stretch overwritten with chunk-like bytes (opcode 6, lengths).
            2 => {
                let at = (next() % input.len() as u64) as usize;
                for (k, b) in input.iter_mut().skip(at).take(64).enumerate() {
                    *b = if k % 9 == 0 { 0x06 } else { next() as u8 };
                }
            }
            // Random bytes after the magic.
            _ => {
                let len = (next() % 4096) as usize;
                input.truncate(8);
                input.extend((0..len).map(|_| next() as u8));
            }
        }
        read_anything(&input);
        answered += 1;
    }
    assert_eq!(answered, 2_000);
}
