//! Raw sensor frames as every source yields them (serial lidar, V4L2 camera,
//! simulator, capture replay): a lidar range frame, an EO colour frame, and a pair
//! of them taken together, owned or shared.

use std::borrow::Borrow;
use std::sync::Arc;

/// One lidar frame: radial range along each pixel's ray, row-major, row 0 at the top.
#[derive(Debug, Clone, PartialEq)]
pub struct RangeFrame {
    pub width: u32,
    pub height: u32,
    /// Radial range in metres (not z-depth); NaN where the lidar saw no return.
    pub ranges_m: Vec<f32>,
    /// Device (or capture) timestamp, nanoseconds.
    pub timestamp_ns: u64,
    /// Frame counter from the source (TXL1 `seq`, MCAP message sequence).
    pub seq: u32,
    /// Optional per-pixel return intensity (arbitrary linear units), same size.
    pub intensity: Option<Vec<f32>>,
}

impl RangeFrame {
    /// A frame of `width x height` with every pixel a no-return.
    pub fn empty(width: u32, height: u32, timestamp_ns: u64, seq: u32) -> Self {
        Self {
            width,
            height,
            ranges_m: vec![f32::NAN; width as usize * height as usize],
            timestamp_ns,
            seq,
            intensity: None,
        }
    }

    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Range at `(u, v)`, `None` for a no-return or a pixel off the frame.
    pub fn range_at(&self, u: u32, v: u32) -> Option<f32> {
        if u >= self.width || v >= self.height {
            return None;
        }
        let r = *self.ranges_m.get((v * self.width + u) as usize)?;
        is_return(r).then_some(r)
    }

    pub fn return_count(&self) -> usize {
        self.ranges_m.iter().filter(|&&r| is_return(r)).count()
    }

    /// True when the buffers have the sizes the header says.
    pub fn is_consistent(&self) -> bool {
        self.ranges_m.len() == self.pixel_count()
            && self
                .intensity
                .as_ref()
                .is_none_or(|i| i.len() == self.pixel_count())
    }
}

/// True for a range value that is a return (finite and positive); NaN, infinities,
/// zero and negative values are no-returns.
#[inline]
pub fn is_return(range_m: f32) -> bool {
    // Two comparisons without a branch between them (NaN fails both), so loops over
    // ranges vectorise.
    (range_m > 0.0) & (range_m < f32::INFINITY)
}

/// One EO frame after conversion to RGB8, row-major, row 0 at the top.
#[derive(Debug, Clone, PartialEq)]
pub struct EoFrame {
    pub width: u32,
    pub height: u32,
    /// `3 * width * height` bytes, R G B per pixel.
    pub rgb: Vec<u8>,
    pub timestamp_ns: u64,
    /// How the frame was exposed, where the camera or the capture says (`None` for
    /// cameras and captures that do not: their pixels are colours, not measurements of
    /// radiance).
    pub exposure: Option<EoExposure>,
}

/// How an EO frame was exposed: with the camera's response curve, what turns its
/// pixel values back into relative radiance (Debevec & Malik 1997: a pixel value is
/// `f(E * exposure_time_s * gain)`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EoExposure {
    /// Shutter (integration) time in seconds.
    pub exposure_time_s: f64,
    /// Sensor gain as a linear factor (1 at the camera's base sensitivity).
    pub gain: f64,
}

/// Longest exposure time accepted (s): beyond any texel camera's, so a larger value is
/// a unit mistake (microseconds written as seconds), not a measurement.
pub const MAX_EXPOSURE_TIME_S: f64 = 3600.0;

/// Largest sensor gain accepted (linear; 2^20 is 120 dB).
pub const MAX_EXPOSURE_GAIN: f64 = 1048576.0;

impl EoExposure {
    /// The factor scene radiance is scaled by before the response curve:
    /// `exposure_time_s * gain`.
    pub fn scale(&self) -> f64 {
        self.exposure_time_s * self.gain
    }

    /// Exposure time and gain finite, positive and within the accepted ranges, so
    /// `scale` is a finite positive number whose log exists.
    pub fn validate(&self) -> Result<(), String> {
        let in_range = |v: f64, max: f64| v.is_finite() && v > 0.0 && v <= max;
        if !in_range(self.exposure_time_s, MAX_EXPOSURE_TIME_S) {
            return Err(format!(
                "exposure_time_s {} is not in (0, {MAX_EXPOSURE_TIME_S}] s",
                self.exposure_time_s
            ));
        }
        if !in_range(self.gain, MAX_EXPOSURE_GAIN) {
            return Err(format!(
                "gain {} is not in (0, {MAX_EXPOSURE_GAIN}]",
                self.gain
            ));
        }
        Ok(())
    }
}

impl EoFrame {
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }

    pub fn is_consistent(&self) -> bool {
        self.rgb.len() == 3 * self.pixel_count()
    }

    /// RGB at `(u, v)`, `None` off the frame.
    pub fn pixel(&self, u: u32, v: u32) -> Option<[u8; 3]> {
        if u >= self.width || v >= self.height {
            return None;
        }
        let i = 3 * (v as usize * self.width as usize + u as usize);
        Some([
            *self.rgb.get(i)?,
            *self.rgb.get(i + 1)?,
            *self.rgb.get(i + 2)?,
        ])
    }
}

/// A lidar frame and the EO frame taken with it: one texel frame. The frames are
/// owned by default; [`SharedFramePair`] holds them behind `Arc`s, so one frame can
/// go to a recorder and to fusion without its pixels being copied.
#[derive(Debug, Clone, PartialEq)]
pub struct FramePair<R = RangeFrame, E = EoFrame> {
    pub range: R,
    pub eo: E,
}

/// A pair of frames shared with whoever else holds them (the daemon's recorder).
pub type SharedFramePair = FramePair<Arc<RangeFrame>, Arc<EoFrame>>;

impl<R: Borrow<RangeFrame>, E> FramePair<R, E> {
    /// The texel frame's timestamp: the lidar's, which fusion's geometry comes from.
    pub fn timestamp_ns(&self) -> u64 {
        self.range.borrow().timestamp_ns
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn returns_and_lookups() {
        let mut f = RangeFrame::empty(3, 2, 7, 1);
        f.ranges_m[4] = 2.5;
        f.ranges_m[0] = 0.0;
        f.ranges_m[1] = f32::INFINITY;
        f.ranges_m[2] = -1.0;
        assert_eq!(f.return_count(), 1);
        assert_eq!(f.range_at(1, 1), Some(2.5));
        assert_eq!(f.range_at(0, 0), None);
        assert_eq!(f.range_at(3, 0), None);
        assert!(f.is_consistent());
        f.intensity = Some(vec![0.0; 5]);
        assert!(!f.is_consistent());
    }
}
