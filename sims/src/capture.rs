//! Writes a simulation as a capture (`docs/capture-format.md`): the sensor model the
//! frames were rendered with (calibrations, `/tf_static`, `/texel/sensor`), then per
//! frame `/lidar/range` (32FC1, exact), `/eo/image` (rgb8) and `/truth/pose`.
//! Rendering of frame i + 1 overlaps the compression and writing of frame i.

use std::path::{Path, PathBuf};

use texel::capture::{CaptureWriter, EoEncoding, PoseTopic, RangeEncoding, WriterOptions};

use crate::simulator::{SimError, SimFrame, Simulator};

/// How a capture is written.
#[derive(Debug, Clone)]
pub struct CaptureOptions {
    pub range_encoding: RangeEncoding,
    pub eo_encoding: EoEncoding,
    pub writer: WriterOptions,
}

impl Default for CaptureOptions {
    fn default() -> Self {
        Self {
            range_encoding: RangeEncoding::F32Metres,
            eo_encoding: EoEncoding::Rgb8,
            writer: WriterOptions::default(),
        }
    }
}

/// What was written.
#[derive(Debug, Clone, PartialEq)]
pub struct CaptureSummary {
    pub path: PathBuf,
    pub frames: usize,
    pub messages: u64,
}

/// Renders every frame of `sim` into a capture at `path`; `progress(done, total)` is
/// called after each frame is written.
pub fn render_capture(
    sim: &Simulator,
    path: &Path,
    options: &CaptureOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<CaptureSummary, SimError> {
    let total = sim.frame_count();
    let mut writer = CaptureWriter::create(path, options.writer.clone())?;
    writer.write_sensor(sim.sensor_model(), sim.timestamp_ns(0))?;
    let mut pending: Option<SimFrame> = Some(sim.frame(0)?);
    let mut done = 0;
    while let Some(frame) = pending.take() {
        let next_index = frame.index + 1;
        let (written, next) = rayon::join(
            || write_frame(&mut writer, &frame, options),
            || {
                (next_index < total)
                    .then(|| sim.frame(next_index))
                    .transpose()
            },
        );
        written?;
        pending = next?;
        done += 1;
        progress(done, total);
    }
    let messages = writer.messages_written();
    writer.finish()?;
    Ok(CaptureSummary {
        path: path.to_path_buf(),
        frames: done,
        messages,
    })
}

fn write_frame<W: std::io::Write + std::io::Seek>(
    writer: &mut CaptureWriter<W>,
    frame: &SimFrame,
    options: &CaptureOptions,
) -> Result<(), SimError> {
    writer.write_range(&frame.pair.range, options.range_encoding)?;
    writer.write_eo(&frame.pair.eo, options.eo_encoding)?;
    writer.write_pose(PoseTopic::Truth, frame.timestamp_ns, &frame.world_from_eo)?;
    Ok(())
}
