//! `texel-bench capture-read [CAPTURE]`: how fast the capture reader (which reads
//! around damage, decoding each chunk whole before yielding it) goes through a
//! capture, against the mcap crate's own streaming `MessageReader` (which gives up at
//! the first damage) on the same file in the same run. Without a capture, a synthetic
//! one (640x480 EO and 320x240 range frames, zstd chunks) is written first.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use mcap::sans_io::{LinearReaderOptions, MessageReadEvent, MessageReader};
use texel::capture::{CaptureReader, CaptureWriter, EoEncoding, RangeEncoding, WriterOptions};
use texel::{EoFrame, RangeFrame};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The capture to read; without one a synthetic capture is written to --work-dir.
    pub capture: Option<PathBuf>,
    /// Frames of the synthetic capture.
    #[arg(long, default_value_t = 200)]
    pub frames: u32,
    /// Timed passes of each reader (alternating, so both see the same machine).
    #[arg(long, default_value_t = 7)]
    pub passes: usize,
    #[arg(long, default_value = "target/bench-capture-read")]
    pub work_dir: PathBuf,
}

pub fn run(args: &Args) -> Result<()> {
    if args.passes == 0 {
        bail!("--passes must be at least 1");
    }
    let capture = match &args.capture {
        Some(c) => c.clone(),
        None => synthetic_capture(&args.work_dir, args.frames)?,
    };
    let bytes = std::fs::metadata(&capture)
        .with_context(|| format!("reading {}", capture.display()))?
        .len();
    let (mut ours, mut baseline) = (Vec::new(), Vec::new());
    let (mut ours_messages, mut baseline_messages) = (0, 0);
    for _ in 0..args.passes {
        let t = Instant::now();
        ours_messages = read_with_capture_reader(&capture)?;
        ours.push(t.elapsed().as_secs_f64());
        let t = Instant::now();
        baseline_messages = read_with_mcap(&capture)?;
        baseline.push(t.elapsed().as_secs_f64());
    }
    if ours_messages != baseline_messages {
        bail!("the readers disagree: {ours_messages} messages against {baseline_messages}");
    }
    let (ours_s, baseline_s) = (median(&mut ours), median(&mut baseline));
    let mib = bytes as f64 / f64::from(1u32 << 20);
    println!(
        "capture: {} ({mib:.1} MiB, {ours_messages} messages), median of {} passes",
        capture.display(),
        args.passes
    );
    println!(
        "  texel CaptureReader          {:8.1} ms  {:7.1} MiB/s",
        ours_s * 1e3,
        mib / ours_s.max(1e-9)
    );
    println!(
        "  mcap MessageReader (baseline) {:7.1} ms  {:7.1} MiB/s",
        baseline_s * 1e3,
        mib / baseline_s.max(1e-9)
    );
    println!(
        "  ratio (CaptureReader / baseline time): {:.2}",
        ours_s / baseline_s.max(1e-9)
    );
    Ok(())
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

fn read_with_capture_reader(path: &Path) -> Result<u64> {
    let mut reader = CaptureReader::open(path)?;
    let mut n = 0;
    while let Some(m) = reader.next_message() {
        m?;
        n += 1;
    }
    Ok(n)
}

/// The baseline: mcap's sans-io message reader over a buffered file, as the capture
/// reader's earlier versions used it.
fn read_with_mcap(path: &Path) -> Result<u64> {
    let mut file = std::io::BufReader::with_capacity(1 << 20, std::fs::File::open(path)?);
    let mut reader = MessageReader::new_with_options(
        LinearReaderOptions::default()
            .with_prevalidate_chunk_crcs(true)
            .with_record_length_limit(512 << 20),
    );
    let mut n = 0;
    while let Some(event) = reader.next_event() {
        match event? {
            MessageReadEvent::ReadRequest(need) => {
                let got = file.read(reader.insert(need))?;
                reader.notify_read(got);
            }
            MessageReadEvent::Message(_) => n += 1,
        }
    }
    Ok(n)
}

/// A capture of `frames` frames with textured, varying content (so zstd has work).
fn synthetic_capture(dir: &Path, frames: u32) -> Result<PathBuf> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let path = dir.join(format!("synthetic-{frames}.mcap"));
    if path.exists() {
        return Ok(path);
    }
    let model = texel::SensorModel {
        name: "bench".into(),
        lidar: texel::PinholeCamera::from_vertical_fov(320, 240, 40.0)?,
        eo: texel::PinholeCamera::from_vertical_fov(640, 480, 40.0)?,
        eo_from_lidar: texel::Pose::identity(),
        range_noise: texel::RangeNoise {
            sigma_m: 0.005,
            sigma_per_m: 0.0,
        },
        range_bias_m: 0.0,
        min_range_m: 0.3,
        max_range_m: 30.0,
        eo_response: None,
    };
    let partial = path.with_extension("partial.mcap");
    let mut w = CaptureWriter::create(&partial, WriterOptions::default())?;
    w.write_sensor(&model, 0)?;
    let mut noise: u32 = 0x9E37_79B9;
    for i in 0..frames {
        let t = u64::from(i) * 33_333_333;
        let mut range = RangeFrame::empty(320, 240, t, i);
        for (k, r) in range.ranges_m.iter_mut().enumerate() {
            noise ^= noise << 13;
            noise ^= noise >> 17;
            noise ^= noise << 5;
            *r = 2.0 + (k % 320) as f32 * 0.01 + (noise % 100) as f32 * 1e-4;
        }
        let rgb = (0..640 * 480 * 3)
            .map(|k: u32| {
                noise ^= noise << 13;
                noise ^= noise >> 17;
                noise ^= noise << 5;
                ((k / 3 % 640) as u8).wrapping_add((noise % 8) as u8)
            })
            .collect();
        let eo = EoFrame {
            width: 640,
            height: 480,
            rgb,
            timestamp_ns: t,
            exposure: None,
        };
        w.write_range(&range, RangeEncoding::F32Metres)?;
        w.write_eo(&eo, EoEncoding::Rgb8)?;
    }
    w.finish()?;
    std::fs::rename(&partial, &path)
        .with_context(|| format!("moving {} into place", partial.display()))?;
    Ok(path)
}
