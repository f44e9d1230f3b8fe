//! `texel-bench txl1`: how fast the TXL1 decoder gets through a hostile stream (a
//! header claiming the largest frame, its span filled with false magics, so a million
//! bad headers and one CRC error) against a clean stream of valid 320x240 frames with
//! intensity (the baseline, same run), each as a multiple of a 921600-baud line.

use std::time::Instant;

use anyhow::{Result, bail};
use texel::fuzzing::{header, test_frame};
use texel::txl1::{MAGIC, MAX_FRAME_LEN, MAX_SIDE, Txl1Decoder};

/// A serial line at 921600 baud carries 8 data bits in 10 bit times.
const LINE_BYTES_PER_S: f64 = 921_600.0 / 10.0;
/// Bytes handed to the decoder at a time, as a serial read would.
const READ_LEN: usize = 64 << 10;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Timed passes over each stream (alternating).
    #[arg(long, default_value_t = 5)]
    pub passes: usize,
}

/// Decodes `stream` in reads; returns (frames, seconds, work units).
fn decode(stream: &[u8]) -> (usize, f64, u64) {
    let started = Instant::now();
    let mut d = Txl1Decoder::new();
    let mut frames = 0;
    for read in stream.chunks(READ_LEN) {
        d.push(read);
        while d.next_frame().is_some() {
            frames += 1;
        }
    }
    (frames, started.elapsed().as_secs_f64(), d.work_units())
}

pub fn run(args: &Args) -> Result<()> {
    if args.passes == 0 {
        bail!("--passes must be at least 1");
    }
    let mut hostile = header(MAX_SIDE, MAX_SIDE, true);
    hostile.extend(MAGIC.repeat((MAX_FRAME_LEN - hostile.len()) / MAGIC.len()));
    let mut clean = Vec::new();
    let mut seq = 0;
    while clean.len() < hostile.len() {
        seq += 1;
        clean.extend(test_frame(320, 240, true, seq).encode());
    }
    let (mut hostile_s, mut clean_s) = (Vec::new(), Vec::new());
    let (mut hostile_work, mut clean_frames) = (0, 0);
    for _ in 0..args.passes {
        let (_, s, work) = decode(&hostile);
        hostile_s.push(s);
        hostile_work = work;
        let (frames, s, _) = decode(&clean);
        clean_s.push(s);
        clean_frames = frames;
    }
    if clean_frames != seq as usize {
        bail!("the clean stream gave {clean_frames} frames of {seq}");
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
    };
    let (h, c) = (median(&mut hostile_s), median(&mut clean_s));
    let rate = |bytes: usize, s: f64| bytes as f64 / s.max(1e-9);
    println!(
        "TXL1 decoder, reads of {} KiB, median of {} passes:",
        READ_LEN >> 10,
        args.passes
    );
    println!(
        "  hostile stream  {:6.2} MiB  {:8.1} ms  {:8.1} MiB/s  {:7.0}x the line  ({:.2} work units a byte)",
        hostile.len() as f64 / f64::from(1u32 << 20),
        h * 1e3,
        rate(hostile.len(), h) / f64::from(1u32 << 20),
        rate(hostile.len(), h) / LINE_BYTES_PER_S,
        hostile_work as f64 / hostile.len() as f64
    );
    println!(
        "  clean stream    {:6.2} MiB  {:8.1} ms  {:8.1} MiB/s  {:7.0}x the line  ({clean_frames} frames)",
        clean.len() as f64 / f64::from(1u32 << 20),
        c * 1e3,
        rate(clean.len(), c) / f64::from(1u32 << 20),
        rate(clean.len(), c) / LINE_BYTES_PER_S,
    );
    println!(
        "  ratio (hostile / clean time per byte): {:.2}",
        (h / hostile.len() as f64) / (c / clean.len() as f64).max(1e-18)
    );
    Ok(())
}
