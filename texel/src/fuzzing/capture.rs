//! The capture reader's fuzz body: arbitrary bytes read as a capture, and a small
//! valid capture damaged as the bytes say (flips, a cut, a stretch overwritten), must
//! each get an answer: events, then at most one fatal error as the last item, every
//! error naming the file, in a number of items bounded by the input's size.

use std::io::Cursor;
use std::sync::OnceLock;

use super::Rng;
use crate::capture::{
    CaptureError, CaptureReader, CaptureWriter, EoEncoding, RangeEncoding, WriterOptions,
};
use crate::frames::{EoFrame, RangeFrame};
use crate::sensor::{RangeNoise, SensorModel};
use crate::{PinholeCamera, Pose};

const NAME: &str = "fuzz.mcap";

/// Reads `bytes` to the end and checks the answer; returns (messages, damaged).
pub fn read_capture(bytes: &[u8]) -> (usize, usize) {
    let (mut messages, mut damaged, mut items) = (0, 0, 0usize);
    let mut ended = false;
    let reader = CaptureReader::new(Cursor::new(bytes), Some(bytes.len() as u64), NAME.into());
    for item in reader {
        assert!(!ended, "an item after a fatal error");
        items += 1;
        assert!(items <= bytes.len() + 2, "more items than bytes");
        match item {
            Ok(_) => messages += 1,
            Err(e) => {
                assert!(
                    e.to_string().starts_with(NAME),
                    "an error not naming the file: {e}"
                );
                if matches!(e, CaptureError::Damaged { .. }) {
                    damaged += 1;
                }
                ended = e.is_fatal();
            }
        }
    }
    (messages, damaged)
}

/// A small valid capture: 6 frames of 8x6 range and 16x12 EO in chunks of a
/// few frames, zstd-compressed, with its summary.
pub fn sample_capture() -> &'static [u8] {
    static SAMPLE: OnceLock<Vec<u8>> = OnceLock::new();
    SAMPLE.get_or_init(|| build_sample().unwrap_or_default())
}

fn build_sample() -> Result<Vec<u8>, CaptureError> {
    let camera = |w, h| PinholeCamera::from_vertical_fov(w, h, 40.0);
    let (Ok(lidar), Ok(eo)) = (camera(8, 6), camera(16, 12)) else {
        return Ok(Vec::new());
    };
    let model = SensorModel {
        name: "fuzz".into(),
        lidar,
        eo,
        eo_from_lidar: Pose::identity(),
        range_noise: RangeNoise {
            sigma_m: 0.005,
            sigma_per_m: 0.0,
        },
        range_bias_m: 0.0,
        min_range_m: 0.3,
        max_range_m: 30.0,
        eo_response: None,
    };
    let options = WriterOptions {
        chunk_size_bytes: 4096,
        ..WriterOptions::default()
    };
    let mut w = CaptureWriter::new(Cursor::new(Vec::new()), options, NAME.into())?;
    w.write_sensor(&model, 0)?;
    for i in 0..6u32 {
        let t = u64::from(i) * 50_000_000;
        let mut range = RangeFrame::empty(8, 6, t, i);
        for (k, r) in range.ranges_m.iter_mut().enumerate() {
            *r = 1.0 + 0.01 * k as f32 + i as f32;
        }
        let eo = EoFrame {
            width: 16,
            height: 12,
            rgb: (0..16 * 12 * 3).map(|k: u32| (k * 7 + i) as u8).collect(),
            timestamp_ns: t,
            exposure: None,
        };
        w.write_range(&range, RangeEncoding::F32Metres)?;
        w.write_eo(&eo, EoEncoding::Rgb8)?;
    }
    Ok(w.finish()?.into_inner())
}

/// The fuzz target's body: `data` read as a capture, then the sample capture damaged
/// as `data` says.
pub fn check_capture(data: &[u8]) {
    read_capture(data);
    let sample = sample_capture();
    if sample.is_empty() || data.is_empty() {
        return;
    }
    let mut seed = [0u8; 8];
    for (s, d) in seed.iter_mut().zip(data) {
        *s = *d;
    }
    let mut rng = Rng::new(u64::from_le_bytes(seed));
    let mut damaged = sample.to_vec();
    let len = damaged.len() as u64;
    match data[0] % 4 {
        0 => {
            for _ in 0..1 + rng.below(16) {
                let at = rng.below(len) as usize;
                damaged[at] ^= (rng.next_u64() as u8) | 1;
            }
        }
        1 => damaged.truncate(rng.below(len) as usize),
        2 => {
            let at = rng.below(len) as usize;
            for (k, b) in damaged.iter_mut().skip(at).take(64).enumerate() {
                *b = if k % 9 == 0 {
                    0x06
                } else {
                    rng.next_u64() as u8
                };
            }
        }
        _ => {
            // The input's own bytes spliced into the sample.
            let at = rng.below(len) as usize;
            for (b, d) in damaged.iter_mut().skip(at).zip(&data[1..]) {
                *b = *d;
            }
        }
    }
    read_capture(&damaged);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sample_reads_whole() {
        let sample = sample_capture();
        assert!(!sample.is_empty());
        // 6 range and 6 EO frames after the sensor messages, no damage.
        let (messages, damaged) = read_capture(sample);
        assert!(messages >= 12, "{messages}");
        assert_eq!(damaged, 0);
    }

    /// The short run kept in CI: seeded inputs through the fuzz body.
    #[test]
    fn seeded_inputs_through_the_fuzz_body() {
        let mut rng = Rng::new(7);
        for _ in 0..3_000 {
            let len = rng.below(600) as usize;
            let data: Vec<u8> = (0..len).map(|_| rng.next_u64() as u8).collect();
            check_capture(&data);
        }
    }
}
