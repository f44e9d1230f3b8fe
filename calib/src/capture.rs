//! Reading a capture of the target into calibration input: every texel frame, the
//! lidar calibration (its intrinsics are taken as known), and the sensor facts the
//! sensor file carries on (range noise, range limits, name). The capture's EO
//! calibration and `/tf_static` are what calibration estimates, so they are ignored.

use std::path::Path;

use texel::capture::{TexelItem, open_texel_frames};

use crate::error::CalibError;
use crate::pipeline::{CalibInput, CalibView};

/// More texel frames than this are not read (a target capture needs tens; 300
/// frames of 640 x 480 are 280 MB in memory).
pub const MAX_VIEWS: usize = 300;

/// Reads a capture of the target. A damaged file yields the frames before the
/// damage, with a warning naming it.
pub fn read_capture(path: &Path) -> Result<CalibInput, CalibError> {
    let mut reader = open_texel_frames(path)?;
    let mut views = Vec::new();
    let mut warnings = Vec::new();
    let mut model = None;
    for item in reader.by_ref() {
        match item {
            Ok(TexelItem::Pair { pair, sensor }) => {
                if views.len() >= MAX_VIEWS {
                    warnings.push(format!("only the first {MAX_VIEWS} texel frames were read"));
                    break;
                }
                if model.is_none() {
                    model = Some(sensor);
                }
                views.push(CalibView {
                    timestamp_ns: pair.timestamp_ns(),
                    pair,
                });
            }
            Ok(TexelItem::Pose { .. } | TexelItem::Anchor(_)) => {}
            Err(e) => {
                let fatal = e.is_fatal();
                // The capture's own extrinsic is not used, so its absence is no news.
                let text = e.to_string();
                if !text.contains("/tf_static") {
                    warnings.push(text);
                }
                if fatal {
                    break;
                }
            }
        }
    }
    let Some(model) = model else {
        return Err(CalibError::Input(format!(
            "{}: no texel frames (a range frame and an EO frame with matching \
             timestamps, after their calibrations){}",
            path.display(),
            warnings
                .first()
                .map(|w| format!("; first problem: {w}"))
                .unwrap_or_default()
        )));
    };
    Ok(CalibInput {
        views,
        lidar: model.lidar.clone(),
        info: model.info(),
        warnings,
    })
}
