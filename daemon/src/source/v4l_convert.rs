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
    })
}
