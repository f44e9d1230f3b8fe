//! Pixel formats a V4L2 camera delivers, converted to the RGB8 every EO frame is.
//! Pure functions on buffer bytes, so they are tested on recorded frames without a
//! device.

use texel::EoFrame;
use texel::capture::{decode_compressed, decode_eo};
use thiserror::Error;

/// The capture formats the source accepts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelFormat {
    /// YUV 4:2:2, Y0 U Y1 V (the common uncompressed webcam format).
    Yuyv,
    /// Motion JPEG: one JPEG per buffer (often without Huffman tables, which the
    /// decoder supplies for AVI1 streams).
    Mjpeg,
    /// RGB24.
    Rgb3,
    /// 8-bit grey.
    Grey,
}

impl PixelFormat {
    /// The V4L2 FourCC.
    pub fn fourcc(self) -> [u8; 4] {
        match self {
            Self::Yuyv => *b"YUYV",
            Self::Mjpeg => *b"MJPG",
            Self::Rgb3 => *b"RGB3",
            Self::Grey => *b"GREY",
        }
    }

    /// Parses a config name (`YUYV`, `MJPEG`/`MJPG`, `RGB3`, `GREY`).
    pub fn from_name(name: &str) -> Option<Self> {
        match name.to_ascii_uppercase().as_str() {
            "YUYV" => Some(Self::Yuyv),
            "MJPEG" | "MJPG" => Some(Self::Mjpeg),
            "RGB3" | "RGB24" => Some(Self::Rgb3),
            "GREY" | "GRAY" => Some(Self::Grey),
            _ => None,
        }
    }

    /// Bytes per pixel of the uncompressed formats.
    fn bytes_per_pixel(self) -> Option<u32> {
        match self {
            Self::Yuyv => Some(2),
            Self::Rgb3 => Some(3),
            Self::Grey => Some(1),
            Self::Mjpeg => None,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum ConvertError {
    #[error(
        "{format:?} buffer of {got} bytes is too short for {width}x{height} with stride {stride}"
    )]
    Short {
        format: PixelFormat,
        got: usize,
        width: u32,
        height: u32,
        stride: u32,
    },
    #[error("{format:?} frame {width}x{height}: {message}")]
    Decode {
        format: PixelFormat,
        width: u32,
        height: u32,
        message: String,
    },
    #[error("MJPEG frame decodes to {got_w}x{got_h}, the stream is {width}x{height}")]
    SizeMismatch {
        got_w: u32,
        got_h: u32,
        width: u32,
        height: u32,
    },
}

/// Converts one buffer (`bytes`, of which the driver filled `bytes.len()`) to an EO
/// frame. `stride` is the driver's bytes per line (0 = packed).
pub fn to_eo_frame(
    format: PixelFormat,
    width: u32,
    height: u32,
    stride: u32,
    bytes: &[u8],
    timestamp_ns: u64,
) -> Result<EoFrame, ConvertError> {
    let rgb = match format.bytes_per_pixel() {
        Some(bpp) => {
            let packed = width.saturating_mul(bpp);
            let stride = if stride == 0 { packed } else { stride };
            let need = u64::from(stride) * u64::from(height.saturating_sub(1)) + u64::from(packed);
            if stride < packed || (bytes.len() as u64) < need {
                return Err(ConvertError::Short {
                    format,
                    got: bytes.len(),
                    width,
                    height,
                    stride,
                });
            }
            let encoding = match format {
                PixelFormat::Yuyv => "yuyv",
                PixelFormat::Rgb3 => "rgb8",
                _ => "mono8",
            };
            // The last line may lack its padding; hand over exactly what is needed.
            let used = &bytes[..need as usize];
            decode_eo(encoding, width, height, stride, used).map_err(|e| ConvertError::Decode {
                format,
                width,
                height,
                message: e.to_string(),
            })?
        }
        None => {
            let (w, h, rgb) =
                decode_compressed("jpeg", bytes).map_err(|e| ConvertError::Decode {
                    format,
                    width,
                    height,
                    message: e.to_string(),
                })?;
            if (w, h) != (width, height) {
                return Err(ConvertError::SizeMismatch {
                    got_w: w,
                    got_h: h,
                    width,
                    height,
                });
            }
            rgb
        }
    };
    Ok(EoFrame {
        width,
        height,
        rgb,
        timestamp_ns,
        exposure: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 16x8 test card: colour bars in pairs of pixels (so YUYV's shared chroma loses
    /// nothing), one grey ramp row.
    fn card() -> (u32, u32, Vec<u8>) {
        let (w, h) = (16u32, 8u32);
        let bars = [
            [255, 255, 255],
            [255, 255, 0],
            [0, 255, 255],
            [0, 255, 0],
            [255, 0, 255],
            [255, 0, 0],
            [0, 0, 255],
            [16, 16, 16],
        ];
        let mut rgb = Vec::new();
        for v in 0..h {
            for u in 0..w {
                if v == h - 1 {
                    let g = (u * 16) as u8;
                    rgb.extend_from_slice(&[g, g, g]);
                } else {
                    rgb.extend_from_slice(&bars[(u / 2) as usize]);
                }
            }
        }
        (w, h, rgb)
    }

    fn max_diff(a: &[u8], b: &[u8]) -> u8 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(x, y)| x.abs_diff(*y))
            .max()
            .unwrap_or(0)
    }

    #[test]
    fn yuyv_known_values() {
        // BT.601 full range: grey stays grey; Y 76 U 85 V 255 is pure red.
        let frame = to_eo_frame(PixelFormat::Yuyv, 2, 1, 0, &[128, 128, 128, 128], 5).unwrap();
        assert_eq!(frame.rgb, [128, 128, 128, 128, 128, 128]);
        assert_eq!(frame.timestamp_ns, 5);
        let red = to_eo_frame(PixelFormat::Yuyv, 2, 1, 0, &[76, 85, 76, 255], 0).unwrap();
        assert!(
            max_diff(&red.rgb, &[255, 0, 0, 255, 0, 0]) <= 2,
            "{:?}",
            red.rgb
        );
    }

    #[test]
    fn yuyv_with_line_padding_matches_the_card() {
        let (w, h, rgb) = card();
        let (step, packed) =
            texel::capture::encode_eo(&rgb, w, h, texel::capture::EoEncoding::Yuyv).unwrap();
        // Pad each line to 40 bytes as drivers do, and drop the last line's padding.
        let stride = 40u32;
        let mut padded = Vec::new();
        for row in packed.chunks(step as usize) {
            padded.extend_from_slice(row);
            padded.extend(std::iter::repeat_n(0xEE, (stride - step) as usize));
        }
        padded.truncate(padded.len() - (stride - step) as usize);
        let frame = to_eo_frame(PixelFormat::Yuyv, w, h, stride, &padded, 1).unwrap();
        assert!(frame.is_consistent());
        assert!(max_diff(&frame.rgb, &rgb) <= 2);
    }

    #[test]
    fn rgb3_and_grey_are_exact() {
        let (w, h, rgb) = card();
        assert_eq!(
            to_eo_frame(PixelFormat::Rgb3, w, h, 0, &rgb, 0)
                .unwrap()
                .rgb,
            rgb
        );
        let grey: Vec<u8> = (0..w * h).map(|i| (i * 2) as u8).collect();
        let f = to_eo_frame(PixelFormat::Grey, w, h, 0, &grey, 0).unwrap();
        for (i, g) in grey.iter().enumerate() {
            assert_eq!(f.rgb[3 * i..3 * i + 3], [*g, *g, *g]);
        }
    }

    fn jpeg(rgb: &[u8], w: u32, h: u32) -> Vec<u8> {
        texel::capture::encode_compressed(rgb, w, h, "jpeg", 95).unwrap()
    }

    /// Removes every DHT segment and adds the AVI1 APP0 marker: how UVC cameras send
    /// MJPEG (the decoder must supply the standard Huffman tables).
    fn as_mjpeg_without_tables(jpeg: &[u8]) -> Vec<u8> {
        let mut out = vec![0xFF, 0xD8, 0xFF, 0xE0, 0x00, 0x08];
        out.extend_from_slice(b"AVI1\0\0");
        let mut i = 2;
        while i + 4 <= jpeg.len() {
            assert_eq!(jpeg[i], 0xFF);
            let marker = jpeg[i + 1];
            if marker == 0xDA {
                out.extend_from_slice(&jpeg[i..]);
                break;
            }
            let len = usize::from(u16::from_be_bytes([jpeg[i + 2], jpeg[i + 3]]));
            if marker != 0xC4 {
                out.extend_from_slice(&jpeg[i..i + 2 + len]);
            }
            i += 2 + len;
        }
        out
    }

    #[test]
    fn mjpeg_with_and_without_huffman_tables() {
        let (w, h, rgb) = card();
        let full = jpeg(&rgb, w, h);
        let f = to_eo_frame(PixelFormat::Mjpeg, w, h, 0, &full, 0).unwrap();
        // Colour bars through JPEG at quality 95 stay close.
        let mean = f
            .rgb
            .iter()
            .zip(&rgb)
            .map(|(a, b)| f64::from(a.abs_diff(*b)))
            .sum::<f64>()
            / rgb.len() as f64;
        assert!(mean < 8.0, "mean error {mean}");
        let bare = as_mjpeg_without_tables(&full);
        assert!(!bare.windows(2).any(|m| m == [0xFF, 0xC4]), "no DHT left");
        let g = to_eo_frame(PixelFormat::Mjpeg, w, h, 0, &bare, 0).unwrap();
        assert_eq!(g.rgb, f.rgb, "the standard tables are the encoder's");
    }

    #[test]
    fn short_and_corrupt_buffers_are_errors_not_panics() {
        let (w, h, rgb) = card();
        for format in [PixelFormat::Yuyv, PixelFormat::Rgb3, PixelFormat::Grey] {
            let e = to_eo_frame(format, w, h, 0, &rgb[..10], 0).unwrap_err();
            assert!(matches!(e, ConvertError::Short { .. }), "{e}");
        }
        // A stride smaller than a line.
        assert!(to_eo_frame(PixelFormat::Rgb3, w, h, 3, &rgb, 0).is_err());
        let e = to_eo_frame(PixelFormat::Mjpeg, w, h, 0, b"\xFF\xD8garbage", 0).unwrap_err();
        assert!(matches!(e, ConvertError::Decode { .. }), "{e}");
        let e = to_eo_frame(PixelFormat::Mjpeg, 32, 8, 0, &jpeg(&rgb, w, h), 0).unwrap_err();
        assert!(matches!(e, ConvertError::SizeMismatch { .. }), "{e}");
        assert_eq!(PixelFormat::from_name("mjpg"), Some(PixelFormat::Mjpeg));
        assert_eq!(PixelFormat::from_name("H264"), None);
    }
}
