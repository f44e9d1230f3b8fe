//! Pixel encodings of the capture format: lidar range (`32FC1`, `16UC1`), lidar
//! intensity (`mono16`, `32FC1`) and EO images (`rgb8`, `bgr8`, `rgba8`, `mono8`,
//! `yuyv`, compressed `jpeg` / `png`), to and from the frame types.
//!
//! Decoders check every size against the declared width, height and row stride
//! before touching the data, and name what is wrong.

use crate::camera::MAX_IMAGE_SIDE;
use crate::frames::is_return;

/// How a range frame is stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum RangeEncoding {
    /// f32 metres; NaN for no return.
    #[default]
    F32Metres,
    /// u16 millimetres; 0 for no return. Ranges beyond 65.534 m and sub-millimetre
    /// detail are lost.
    U16Millimetres,
}

impl RangeEncoding {
    pub fn name(self) -> &'static str {
        match self {
            Self::F32Metres => "32FC1",
            Self::U16Millimetres => "16UC1",
        }
    }
}

/// How an EO frame is stored as a `foxglove.RawImage`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum EoEncoding {
    #[default]
    Rgb8,
    Bgr8,
    Rgba8,
    /// Grey (lossy for colour frames: ITU-R BT.601 luma).
    Mono8,
    /// YUV 4:2:2, bytes Y0 U Y1 V (lossy: chroma shared by pixel pairs).
    Yuyv,
}

impl EoEncoding {
    pub const ALL: [EoEncoding; 5] = [Self::Rgb8, Self::Bgr8, Self::Rgba8, Self::Mono8, Self::Yuyv];

    pub fn name(self) -> &'static str {
        match self {
            Self::Rgb8 => "rgb8",
            Self::Bgr8 => "bgr8",
            Self::Rgba8 => "rgba8",
            Self::Mono8 => "mono8",
            Self::Yuyv => "yuyv",
        }
    }

    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|e| e.name() == name)
    }

    /// Bytes per pixel (YUYV: 2, two pixels share 4 bytes).
    pub fn bytes_per_pixel(self) -> usize {
        match self {
            Self::Rgb8 | Self::Bgr8 => 3,
            Self::Rgba8 => 4,
            Self::Mono8 => 1,
            Self::Yuyv => 2,
        }
    }
}

/// A pixel buffer that does not match its declared layout.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ImageError {
    #[error("image size {width}x{height} is outside 1..={MAX_IMAGE_SIDE} per side")]
    BadSize { width: u32, height: u32 },
    #[error("unsupported encoding {0:?}")]
    UnsupportedEncoding(String),
    #[error("row stride {step} is smaller than a row of {width} pixels at {bpp} bytes each")]
    StrideTooSmall { step: u32, width: u32, bpp: usize },
    #[error("data holds {actual} bytes, {expected} needed for {height} rows of stride {step}")]
    DataTooShort {
        actual: usize,
        expected: usize,
        height: u32,
        step: u32,
    },
    #[error("yuyv needs an even width, got {0}")]
    OddYuyvWidth(u32),
    #[error("cannot decode {format} image: {message}")]
    Compressed { format: String, message: String },
}

fn check_size(width: u32, height: u32) -> Result<(), ImageError> {
    if width == 0 || height == 0 || width > MAX_IMAGE_SIDE || height > MAX_IMAGE_SIDE {
        return Err(ImageError::BadSize { width, height });
    }
    Ok(())
}

/// Validates the layout and returns each row's bytes (without padding).
fn rows(
    data: &[u8],
    width: u32,
    height: u32,
    step: u32,
    bpp: usize,
) -> Result<impl Iterator<Item = &[u8]>, ImageError> {
    check_size(width, height)?;
    let row_bytes = width as usize * bpp;
    if (step as usize) < row_bytes {
        return Err(ImageError::StrideTooSmall { step, width, bpp });
    }
    // The last row needs only its pixels, not the full stride.
    let expected = step as usize * (height as usize - 1) + row_bytes;
    if data.len() < expected {
        return Err(ImageError::DataTooShort {
            actual: data.len(),
            expected,
            height,
            step,
        });
    }
    Ok((0..height as usize).map(move |r| {
        let start = r * step as usize;
        &data[start..start + row_bytes]
    }))
}

/// Range pixels to bytes; returns `(encoding name, step, data)`.
pub fn encode_range(ranges_m: &[f32], width: u32, encoding: RangeEncoding) -> (u32, Vec<u8>) {
    match encoding {
        RangeEncoding::F32Metres => {
            let mut out = Vec::with_capacity(ranges_m.len() * 4);
            for &r in ranges_m {
                let r = if is_return(r) { r } else { f32::NAN };
                out.extend_from_slice(&r.to_le_bytes());
            }
            (width * 4, out)
        }
        RangeEncoding::U16Millimetres => {
            let mut out = Vec::with_capacity(ranges_m.len() * 2);
            for &r in ranges_m {
                let mm = if is_return(r) {
                    // Round to the nearest millimetre; clamp into 1..=65534 so a
                    // return never turns into the no-return value 0.
                    (f64::from(r) * 1000.0).round().clamp(1.0, 65534.0) as u16
                } else {
                    0
                };
                out.extend_from_slice(&mm.to_le_bytes());
            }
            (width * 2, out)
        }
    }
}

/// Bytes to range pixels in metres (NaN for no return).
pub fn decode_range(
    encoding: &str,
    width: u32,
    height: u32,
    step: u32,
    data: &[u8],
) -> Result<Vec<f32>, ImageError> {
    let mut out = Vec::new();
    match encoding {
        "32FC1" => {
            let rows = rows(data, width, height, step, 4)?;
            out.reserve_exact(width as usize * height as usize);
            for row in rows {
                for px in row.chunks_exact(4) {
                    let r = f32::from_le_bytes([px[0], px[1], px[2], px[3]]);
                    out.push(if is_return(r) { r } else { f32::NAN });
                }
            }
        }
        "16UC1" => {
            let rows = rows(data, width, height, step, 2)?;
            out.reserve_exact(width as usize * height as usize);
            for row in rows {
                for px in row.chunks_exact(2) {
                    let mm = u16::from_le_bytes([px[0], px[1]]);
                    out.push(if mm == 0 {
                        f32::NAN
                    } else {
                        f32::from(mm) / 1000.0
                    });
                }
            }
        }
        other => return Err(ImageError::UnsupportedEncoding(other.to_string())),
    }
    Ok(out)
}

/// Intensity pixels to `mono16` bytes, or `32FC1` if any value does not fit u16.
pub fn encode_intensity(values: &[f32], width: u32) -> (&'static str, u32, Vec<u8>) {
    let fits = values
        .iter()
        .all(|&v| v.is_finite() && (0.0..=65535.0).contains(&v) && v.fract() == 0.0);
    if fits {
        let mut out = Vec::with_capacity(values.len() * 2);
        for &v in values {
            out.extend_from_slice(&(v as u16).to_le_bytes());
        }
        ("mono16", width * 2, out)
    } else {
        let mut out = Vec::with_capacity(values.len() * 4);
        for &v in values {
            out.extend_from_slice(&v.to_le_bytes());
        }
        ("32FC1", width * 4, out)
    }
}

pub fn decode_intensity(
    encoding: &str,
    width: u32,
    height: u32,
    step: u32,
    data: &[u8],
) -> Result<Vec<f32>, ImageError> {
    let mut out = Vec::new();
    match encoding {
        "mono16" => {
            let rows = rows(data, width, height, step, 2)?;
            out.reserve_exact(width as usize * height as usize);
            for row in rows {
                out.extend(
                    row.chunks_exact(2)
                        .map(|p| f32::from(u16::from_le_bytes([p[0], p[1]]))),
                );
            }
        }
        "32FC1" => {
            let rows = rows(data, width, height, step, 4)?;
            out.reserve_exact(width as usize * height as usize);
            for row in rows {
                out.extend(
                    row.chunks_exact(4)
                        .map(|p| f32::from_le_bytes([p[0], p[1], p[2], p[3]])),
                );
            }
        }
        other => return Err(ImageError::UnsupportedEncoding(other.to_string())),
    }
    Ok(out)
}

/// ITU-R BT.601 luma of an RGB pixel, rounded.
fn luma(r: u8, g: u8, b: u8) -> u8 {
    let y = 0.299 * f32::from(r) + 0.587 * f32::from(g) + 0.114 * f32::from(b);
    y.round().clamp(0.0, 255.0) as u8
}

/// Full-range BT.601 YCbCr to RGB (the form V4L2 YUYV cameras and the capture
/// format's `yuyv` use).
fn ycbcr_to_rgb(y: u8, cb: u8, cr: u8) -> [u8; 3] {
    let y = f32::from(y);
    let cb = f32::from(cb) - 128.0;
    let cr = f32::from(cr) - 128.0;
    let clamp = |v: f32| v.round().clamp(0.0, 255.0) as u8;
    [
        clamp(y + 1.402 * cr),
        clamp(y - 0.344_136 * cb - 0.714_136 * cr),
        clamp(y + 1.772 * cb),
    ]
}

fn rgb_to_ycbcr(p: [u8; 3]) -> [f32; 3] {
    let (r, g, b) = (f32::from(p[0]), f32::from(p[1]), f32::from(p[2]));
    [
        0.299 * r + 0.587 * g + 0.114 * b,
        128.0 - 0.168_736 * r - 0.331_264 * g + 0.5 * b,
        128.0 + 0.5 * r - 0.418_688 * g - 0.081_312 * b,
    ]
}

/// RGB8 pixels to bytes in `encoding`; returns `(step, data)`.
pub fn encode_eo(
    rgb: &[u8],
    width: u32,
    height: u32,
    encoding: EoEncoding,
) -> Result<(u32, Vec<u8>), ImageError> {
    check_size(width, height)?;
    let pixels = rgb.chunks_exact(3);
    let step = width * encoding.bytes_per_pixel() as u32;
    let data = match encoding {
        EoEncoding::Rgb8 => rgb.to_vec(),
        EoEncoding::Bgr8 => pixels.flat_map(|p| [p[2], p[1], p[0]]).collect(),
        EoEncoding::Rgba8 => pixels.flat_map(|p| [p[0], p[1], p[2], 255]).collect(),
        EoEncoding::Mono8 => pixels.map(|p| luma(p[0], p[1], p[2])).collect(),
        EoEncoding::Yuyv => {
            if !width.is_multiple_of(2) {
                return Err(ImageError::OddYuyvWidth(width));
            }
            let mut out = Vec::with_capacity(width as usize * height as usize * 2);
            for pair in rgb.chunks_exact(6) {
                let a = rgb_to_ycbcr([pair[0], pair[1], pair[2]]);
                let b = rgb_to_ycbcr([pair[3], pair[4], pair[5]]);
                let q = |v: f32| v.round().clamp(0.0, 255.0) as u8;
                out.extend_from_slice(&[
                    q(a[0]),
                    q(0.5 * (a[1] + b[1])),
                    q(b[0]),
                    q(0.5 * (a[2] + b[2])),
                ]);
            }
            out
        }
    };
    Ok((step, data))
}

/// Bytes in one of the capture format's raw encodings to RGB8.
pub fn decode_eo(
    encoding: &str,
    width: u32,
    height: u32,
    step: u32,
    data: &[u8],
) -> Result<Vec<u8>, ImageError> {
    let encoding = EoEncoding::from_name(encoding)
        .ok_or_else(|| ImageError::UnsupportedEncoding(encoding.to_string()))?;
    if encoding == EoEncoding::Yuyv && !width.is_multiple_of(2) {
        return Err(ImageError::OddYuyvWidth(width));
    }
    let rows = rows(data, width, height, step, encoding.bytes_per_pixel())?;
    let mut out = Vec::with_capacity(width as usize * height as usize * 3);
    for row in rows {
        match encoding {
            EoEncoding::Rgb8 => out.extend_from_slice(row),
            EoEncoding::Bgr8 => out.extend(row.chunks_exact(3).flat_map(|p| [p[2], p[1], p[0]])),
            EoEncoding::Rgba8 => out.extend(row.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]])),
            EoEncoding::Mono8 => out.extend(row.iter().flat_map(|&g| [g, g, g])),
            EoEncoding::Yuyv => {
                for q in row.chunks_exact(4) {
                    out.extend_from_slice(&ycbcr_to_rgb(q[0], q[1], q[3]));
                    out.extend_from_slice(&ycbcr_to_rgb(q[2], q[1], q[3]));
                }
            }
        }
    }
    Ok(out)
}

/// A `jpeg` or `png` image to `(width, height, RGB8)`, refusing sizes past the limit
/// before decoding the pixels.
pub fn decode_compressed(format: &str, data: &[u8]) -> Result<(u32, u32, Vec<u8>), ImageError> {
    let image_format = match format {
        "jpeg" | "jpg" => image::ImageFormat::Jpeg,
        "png" => image::ImageFormat::Png,
        other => return Err(ImageError::UnsupportedEncoding(other.to_string())),
    };
    let err = |message: String| ImageError::Compressed {
        format: format.to_string(),
        message,
    };
    let mut reader = image::ImageReader::with_format(std::io::Cursor::new(data), image_format);
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(MAX_IMAGE_SIDE);
    limits.max_image_height = Some(MAX_IMAGE_SIDE);
    limits.max_alloc = Some(u64::from(MAX_IMAGE_SIDE) * u64::from(MAX_IMAGE_SIDE) * 4);
    reader.limits(limits);
    let decoded = reader.decode().map_err(|e| err(e.to_string()))?;
    let rgb = decoded.to_rgb8();
    let (w, h) = rgb.dimensions();
    check_size(w, h)?;
    Ok((w, h, rgb.into_raw()))
}

/// RGB8 to a compressed `png` or `jpeg` (quality 0-100).
pub fn encode_compressed(
    rgb: &[u8],
    width: u32,
    height: u32,
    format: &str,
    jpeg_quality: u8,
) -> Result<Vec<u8>, ImageError> {
    check_size(width, height)?;
    let err = |message: String| ImageError::Compressed {
        format: format.to_string(),
        message,
    };
    let mut out = Vec::new();
    match format {
        "png" => {
            let encoder = image::codecs::png::PngEncoder::new(&mut out);
            image::ImageEncoder::write_image(
                encoder,
                rgb,
                width,
                height,
                image::ExtendedColorType::Rgb8,
            )
            .map_err(|e| err(e.to_string()))?;
        }
        "jpeg" => {
            let encoder =
                image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, jpeg_quality);
            image::ImageEncoder::write_image(
                encoder,
                rgb,
                width,
                height,
                image::ExtendedColorType::Rgb8,
            )
            .map_err(|e| err(e.to_string()))?;
        }
        other => return Err(ImageError::UnsupportedEncoding(other.to_string())),
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gradient(width: u32, height: u32) -> Vec<u8> {
        (0..width * height)
            .flat_map(|i| {
                [
                    (i * 7 % 256) as u8,
                    (i * 13 % 256) as u8,
                    (i * 29 % 256) as u8,
                ]
            })
            .collect()
    }

    #[test]
    fn lossless_eo_encodings_round_trip_exactly() {
        let rgb = gradient(6, 4);
        for enc in [EoEncoding::Rgb8, EoEncoding::Bgr8, EoEncoding::Rgba8] {
            let (step, data) = encode_eo(&rgb, 6, 4, enc).unwrap();
            assert_eq!(
                decode_eo(enc.name(), 6, 4, step, &data).unwrap(),
                rgb,
                "{enc:?}"
            );
        }
    }

    #[test]
    fn mono_and_yuyv_keep_grey_exactly() {
        let grey: Vec<u8> = (0..24u8).flat_map(|g| [g * 10, g * 10, g * 10]).collect();
        for enc in [EoEncoding::Mono8, EoEncoding::Yuyv] {
            let (step, data) = encode_eo(&grey, 6, 4, enc).unwrap();
            let back = decode_eo(enc.name(), 6, 4, step, &data).unwrap();
            for (a, b) in grey.iter().zip(&back) {
                assert!(a.abs_diff(*b) <= 1, "{enc:?}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn yuyv_colour_is_close() {
        // Pairs of equal pixels lose nothing to chroma sharing.
        let rgb: Vec<u8> = [[200u8, 30, 60], [10, 180, 90], [40, 50, 220]]
            .iter()
            .flat_map(|p| [*p, *p])
            .flatten()
            .collect();
        let (step, data) = encode_eo(&rgb, 6, 1, EoEncoding::Yuyv).unwrap();
        let back = decode_eo("yuyv", 6, 1, step, &data).unwrap();
        for (a, b) in rgb.iter().zip(&back) {
            assert!(a.abs_diff(*b) <= 2, "{a} vs {b}");
        }
    }

    #[test]
    fn padded_rows_are_honoured() {
        // 2x2 rgb8 with 2 bytes of padding per row.
        let data = [1, 2, 3, 4, 5, 6, 0, 0, 7, 8, 9, 10, 11, 12];
        let rgb = decode_eo("rgb8", 2, 2, 8, &data).unwrap();
        assert_eq!(rgb, [1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12]);
    }

    #[test]
    fn bad_layouts_are_named() {
        assert!(matches!(
            decode_eo("rgb8", 2, 2, 5, &[0; 12]),
            Err(ImageError::StrideTooSmall { .. })
        ));
        assert!(matches!(
            decode_eo("rgb8", 2, 2, 6, &[0; 11]),
            Err(ImageError::DataTooShort { .. })
        ));
        assert!(matches!(
            decode_eo("bayer_rggb8", 2, 2, 2, &[0; 4]),
            Err(ImageError::UnsupportedEncoding(_))
        ));
        assert!(matches!(
            decode_range("32FC1", 0, 2, 0, &[]),
            Err(ImageError::BadSize { .. })
        ));
        assert!(matches!(
            decode_range("32FC1", 100_000, 1, 400_000, &[]),
            Err(ImageError::BadSize { .. })
        ));
    }

    #[test]
    fn range_encodings_and_no_returns() {
        let ranges = [1.2345f32, f32::NAN, 0.0, f32::INFINITY, 70.0, 0.0004];
        let (step, data) = encode_range(&ranges, 6, RangeEncoding::F32Metres);
        let back = decode_range("32FC1", 6, 1, step, &data).unwrap();
        assert_eq!(back[0], 1.2345);
        assert!(back[1].is_nan() && back[2].is_nan() && back[3].is_nan());
        let (step, data) = encode_range(&ranges, 6, RangeEncoding::U16Millimetres);
        let back = decode_range("16UC1", 6, 1, step, &data).unwrap();
        assert!((back[0] - 1.235).abs() < 1e-6);
        assert!(back[1].is_nan() && back[2].is_nan() && back[3].is_nan());
        assert!(
            (back[4] - 65.534).abs() < 1e-4,
            "clamped to the largest count"
        );
        assert!((back[5] - 0.001).abs() < 1e-6, "a return never becomes 0");
    }

    #[test]
    fn compressed_round_trip() {
        let rgb = gradient(16, 8);
        let png = encode_compressed(&rgb, 16, 8, "png", 90).unwrap();
        assert_eq!(
            decode_compressed("png", &png).unwrap(),
            (16, 8, rgb.clone())
        );
        let jpg = encode_compressed(&rgb, 16, 8, "jpeg", 95).unwrap();
        let (w, h, _) = decode_compressed("jpeg", &jpg).unwrap();
        assert_eq!((w, h), (16, 8));
        assert!(decode_compressed("png", &[1, 2, 3]).is_err());
    }
}
