//! A capture with a damaged chunk, through the real `texeld` binary: `info` lists the
//! stretch it read around and the log times it cost, and `replay` places every frame
//! outside it and counts the damage.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::path::Path;
use std::process::Command;

use texel::capture::PoseTopic;
use texel_e2e::captures;

const FRAMES: u32 = 40;
const PERIOD_NS: u64 = 50_000_000;

/// Writes a capture in small chunks, flips one byte in the middle of a chunk half way
/// through, and returns how many range and EO frames that chunk held (read with the
/// mcap crate's own chunk reader before the flip).
fn damaged_capture(path: &Path) -> (usize, usize) {
    captures::write_chunked(path, FRAMES, PERIOD_NS, Some(PoseTopic::Truth), 8 << 10);
    let mut bytes = std::fs::read(path).unwrap();
    let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
    let mut chunks = summary.chunk_indexes.clone();
    chunks.sort_by_key(|c| c.chunk_start_offset);
    let chunk = &chunks[chunks.len() / 2];
    let start = chunk.chunk_start_offset as usize;
    let body = &bytes[start + 9..start + chunk.chunk_length as usize];
    let mcap::records::Record::Chunk { header, data } = mcap::parse_record(0x06, body).unwrap()
    else {
        panic!("no chunk at {start}");
    };
    let (mut ranges, mut eos) = (0, 0);
    for record in mcap::read::ChunkReader::new(header, &data).unwrap() {
        if let mcap::records::Record::Message { header, .. } = record.unwrap() {
            match summary.channels[&header.channel_id].topic.as_str() {
                "/lidar/range" => ranges += 1,
                "/eo/image" => eos += 1,
                _ => {}
            }
        }
    }
    let at = start + chunk.chunk_length as usize / 2 + 20;
    bytes[at] ^= 0x5A;
    std::fs::write(path, bytes).unwrap();
    (ranges, eos)
}

fn texeld(args: &[&str], capture: &Path) -> (Option<i32>, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_texeld"))
        .arg(args[0])
        .arg(capture)
        .args(&args[1..])
        .output()
        .unwrap();
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn info_lists_the_stretch_it_read_around_and_the_times_it_cost() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("damaged.mcap");
    let (lost_ranges, lost_eos) = damaged_capture(&capture);
    assert!(lost_ranges + lost_eos >= 1);
    let (_, out, err) = texeld(&["info"], &capture);
    assert!(
        out.contains("damaged stretches read around: 1"),
        "{out}{err}"
    );
    assert!(out.contains("are lost"), "{out}");
    let (ranges, eos) = (FRAMES as usize - lost_ranges, FRAMES as usize - lost_eos);
    assert!(
        out.contains(&format!("frames: {ranges} range, {eos} EO")),
        "{out}"
    );
}

#[test]
fn one_damaged_byte_ends_nothing_but_its_chunk() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("damaged.mcap");
    let (lost_ranges, lost_eos) = damaged_capture(&capture);
    let (code, out, err) = texeld(
        &["replay", "--fast", "--no-serve", "--capture-poses"],
        &capture,
    );
    assert_eq!(code, Some(0), "{out}{err}");
    let scans: usize = out
        .split_whitespace()
        .nth(1)
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{out}"));
    // A frame is placed when both its halves survived.
    let most = FRAMES as usize - lost_ranges.max(lost_eos);
    let least = FRAMES as usize - lost_ranges - lost_eos;
    assert!(scans >= least && scans <= most, "{scans} scans: {out}{err}");
    assert!(scans >= FRAMES as usize - 3, "{scans} scans: {out}{err}");
    assert!(err.contains("damaged"), "{err}");
}
