//! Version 4's messages for radiance: `ScanExposure` (how a scan's EO frame was
//! exposed, sent before its `ScanAdded`) and `EoResponse` (the camera's response
//! curve, sent once in the snapshot). With them a viewer turns the scans' 8-bit
//! textures into radiance by a table lookup: the texture travels as it always did
//! (JPEG by default, a sixth of raw), 16 bytes more per scan and 6 KiB per session,
//! where a float texture would travel at 8 bytes a pixel.

use super::bytes_in::{BodyReader, PutLe};
use super::{ScanId, WireError};
use crate::EoExposure;
use crate::radiance::{EoResponse, LEVELS};

/// `u64 id, f64 exposure_time_s, f64 gain`.
pub(super) fn put_scan_exposure(
    out: &mut Vec<u8>,
    id: ScanId,
    exposure: &EoExposure,
) -> Result<(), WireError> {
    exposure
        .validate()
        .map_err(|m| WireError::encode("ScanExposure", m))?;
    out.put_u64(id);
    out.put_f64(exposure.exposure_time_s);
    out.put_f64(exposure.gain);
    Ok(())
}

pub(super) fn read_scan_exposure(body: &[u8]) -> Result<(ScanId, EoExposure), WireError> {
    let mut r = BodyReader::new(body, "ScanExposure");
    let id = r.u64("id")?;
    let exposure = EoExposure {
        exposure_time_s: r.f64("exposure_time_s")?,
        gain: r.f64("gain")?,
    };
    r.finish()?;
    exposure
        .validate()
        .map_err(|m| WireError::invalid("ScanExposure", m))?;
    Ok((id, exposure))
}

/// Bytes of an `EoResponse` body: three channels of 256 f64 values.
pub const EO_RESPONSE_LEN: usize = 3 * LEVELS * 8;

/// The red, green and blue curves, 256 `f64` of ln exposure each.
pub(super) fn put_eo_response(out: &mut Vec<u8>, response: &EoResponse) {
    for curve in response.curves() {
        for &g in curve {
            out.put_f64(g);
        }
    }
}

pub(super) fn read_eo_response(body: &[u8]) -> Result<EoResponse, WireError> {
    let mut r = BodyReader::new(body, "EoResponse");
    let mut curves: [Vec<f64>; 3] = Default::default();
    for curve in &mut curves {
        for _ in 0..LEVELS {
            curve.push(r.f64("curve")?);
        }
    }
    r.finish()?;
    // The curve's own rules: finite, monotone within tolerance.
    EoResponse::new(curves).map_err(|e| WireError::invalid("EoResponse", e.to_string()))
}
