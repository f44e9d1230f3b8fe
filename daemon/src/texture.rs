//! Texture compression for the stream: JPEG through `jpeg-encoder` (SIMD, several
//! times faster than the `image` crate's encoder on the same image; `texel-bench daemon`
//! measures both), PNG and raw RGB through `texel::wire::Texture::encode`.

use texel::EoFrame;
use texel::wire::{Texture, TextureFormat, WireError};

/// Compresses an EO frame for the wire.
pub fn encode(
    frame: &EoFrame,
    format: TextureFormat,
    jpeg_quality: u8,
) -> Result<Texture, WireError> {
    if format != TextureFormat::Jpeg {
        return Texture::encode(frame, format, jpeg_quality);
    }
    let too_big = || Texture::encode(frame, format, jpeg_quality);
    let (Ok(w), Ok(h)) = (u16::try_from(frame.width), u16::try_from(frame.height)) else {
        return too_big();
    };
    if !frame.is_consistent() {
        return too_big();
    }
    let mut data = Vec::with_capacity(frame.rgb.len() / 8);
    let encoder = jpeg_encoder::Encoder::new(&mut data, jpeg_quality.clamp(1, 100));
    match encoder.encode(&frame.rgb, w, h, jpeg_encoder::ColorType::Rgb) {
        Ok(()) => Ok(Texture {
            format,
            width: frame.width,
            height: frame.height,
            timestamp_ns: frame.timestamp_ns,
            data,
        }),
        // The image crate's encoder as a fallback, with its own error if it fails too.
        Err(_) => too_big(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jpeg_textures_decode_to_the_image_within_jpeg_error() {
        let (w, h) = (96u32, 64u32);
        let rgb: Vec<u8> = (0..w * h)
            .flat_map(|i| {
                let (x, y) = (i % w, i / w);
                [(x * 2) as u8, (y * 3) as u8, ((x + y) % 256) as u8]
            })
            .collect();
        let frame = EoFrame {
            width: w,
            height: h,
            rgb,
            timestamp_ns: 42,
            exposure: None,
        };
        let t = encode(&frame, TextureFormat::Jpeg, 90).unwrap();
        assert!(t.data.len() < frame.rgb.len() / 4);
        let back = t.decode().unwrap();
        assert_eq!((back.width, back.height, back.timestamp_ns), (w, h, 42));
        let mean = back
            .rgb
            .iter()
            .zip(&frame.rgb)
            .map(|(a, b)| f64::from(a.abs_diff(*b)))
            .sum::<f64>()
            / frame.rgb.len() as f64;
        assert!(mean < 3.0, "mean error {mean}");
        let png = encode(&frame, TextureFormat::Png, 90).unwrap();
        assert_eq!(png.decode().unwrap().rgb, frame.rgb);
    }
}
