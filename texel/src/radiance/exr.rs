//! Radiance images as OpenEXR: linear RGB in 32-bit floats, lossless. The simulator
//! writes its radiance truth so (high-dynamic-range results are scored against the
//! radiance the scene sends to the camera, not against an 8-bit picture of it), and
//! the viewer tone-maps such files.

use std::path::Path;

/// Linear RGB.
pub type Rgb = [f32; 3];

/// Largest radiance image read back (pixels): beyond any texel camera's EO image, so
/// a hostile header cannot make the reader allocate without bound.
pub const MAX_EXR_PIXELS: usize = 64 << 20;

/// Why a radiance image could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum ExrError {
    #[error("{path}: {message}")]
    Exr { path: String, message: String },
    #[error("{path}: {width}x{height} has {pixels} pixels, the image {given} values")]
    Size {
        path: String,
        width: u32,
        height: u32,
        pixels: usize,
        given: usize,
    },
}

/// Writes `width × height` linear RGB values (row-major, row 0 at the top) as a
/// 32-bit float OpenEXR file. Non-finite or negative values are written as 0, as
/// radiance is finite and non-negative.
pub fn write_radiance_exr(
    path: &Path,
    width: u32,
    height: u32,
    radiance: &[Rgb],
) -> Result<(), ExrError> {
    let pixels = width as usize * height as usize;
    if radiance.len() != pixels || pixels == 0 {
        return Err(ExrError::Size {
            path: path.display().to_string(),
            width,
            height,
            pixels,
            given: radiance.len(),
        });
    }
    let w = width as usize;
    let clean = |v: f32| if v.is_finite() && v > 0.0 { v } else { 0.0 };
    exr::prelude::write_rgb_file(path, w, height as usize, |x, y| {
        let p = radiance.get(y * w + x).copied().unwrap_or([0.0; 3]);
        (clean(p[0]), clean(p[1]), clean(p[2]))
    })
    .map_err(|e| ExrError::Exr {
        path: path.display().to_string(),
        message: e.to_string(),
    })
}

/// A radiance image read back: width, height and linear RGB per pixel. Refuses an
/// image larger than [`MAX_EXR_PIXELS`] before reading its pixels.
pub fn read_radiance_exr(path: &Path) -> Result<(u32, u32, Vec<Rgb>), ExrError> {
    let error = |message: String| ExrError::Exr {
        path: path.display().to_string(),
        message,
    };
    let meta = exr::meta::MetaData::read_from_file(path, false)
        .map_err(|e| error(format!("not a readable OpenEXR file: {e}")))?;
    let size = meta
        .headers
        .first()
        .map(|h| h.layer_size)
        .ok_or_else(|| error("no layer".into()))?;
    let (w, h) = (size.width(), size.height());
    if w == 0 || h == 0 || w.saturating_mul(h) > MAX_EXR_PIXELS {
        return Err(error(format!(
            "a {w}x{h} image is outside 1..={MAX_EXR_PIXELS} pixels"
        )));
    }
    let image = exr::prelude::read_first_rgba_layer_from_file(
        path,
        |resolution, _| vec![[0.0f32; 3]; resolution.width() * resolution.height()],
        move |pixels: &mut Vec<Rgb>, position, (r, g, b, _a): (f32, f32, f32, f32)| {
            if let Some(p) = pixels.get_mut(position.y() * w + position.x()) {
                *p = [r, g, b];
            }
        },
    )
    .map_err(|e| error(e.to_string()))?;
    let pixels = image.layer_data.channel_data.pixels;
    if pixels.len() != w * h {
        return Err(error(format!(
            "the first layer has {} pixels, its header says {w}x{h}",
            pixels.len()
        )));
    }
    Ok((w as u32, h as u32, pixels))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radiance_round_trips_exactly_and_bad_values_become_zero() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.exr");
        let mut values: Vec<Rgb> = (0..6 * 4)
            .map(|i| [i as f32 * 1.5e-3, 1.0e4 / (1.0 + i as f32), 0.25])
            .collect();
        values[3] = [f32::NAN, f32::INFINITY, -2.0];
        write_radiance_exr(&path, 6, 4, &values).unwrap();
        let (w, h, back) = read_radiance_exr(&path).unwrap();
        assert_eq!((w, h), (6, 4));
        values[3] = [0.0; 3];
        assert_eq!(back, values);
    }

    #[test]
    fn wrong_sizes_and_non_exr_files_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.exr");
        let e = write_radiance_exr(&path, 3, 3, &[[0.0; 3]; 8]).unwrap_err();
        assert!(e.to_string().contains("3x3 has 9 pixels"), "{e}");
        std::fs::write(&path, b"not an exr").unwrap();
        let e = read_radiance_exr(&path).unwrap_err();
        assert!(e.to_string().contains("not a readable OpenEXR"), "{e}");
    }
}
