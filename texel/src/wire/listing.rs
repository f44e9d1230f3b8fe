//! The fields of the version 2 messages that list, withdraw and fetch scans by id:
//! a scan's listing (`ScanListed`), its withdrawal, a client's request for its data
//! and the server's answer that a request cannot be met. Each field is validated on
//! decode (finite numbers, bounds with min <= max) and refused on encode likewise, so
//! whatever encodes also decodes.

use super::bytes_in::{BodyReader, PutLe};
use super::{MAX_REASON_LEN, WireError, put_pose, put_string, read_pose};
use crate::model::{ScanId, ScanListing};
use crate::pose::Pose;

/// Bytes of a listing on the wire: timestamp, 9 f32 (bounds, centre), priority,
/// encoded size.
pub const LISTING_LEN: usize = 8 + 9 * 4 + 4 + 8;

/// Why a listing is not sendable (or not accepted), if it is not.
fn check_listing(l: &ScanListing) -> Result<(), String> {
    let floats = l
        .bounds_min_m
        .iter()
        .chain(&l.bounds_max_m)
        .chain(&l.cop_m)
        .chain(std::iter::once(&l.priority));
    if floats.into_iter().any(|v| !v.is_finite()) {
        return Err("non-finite bounds, centre or priority".into());
    }
    if let Some(axis) = (0..3).find(|&k| l.bounds_min_m[k] > l.bounds_max_m[k]) {
        return Err(format!("bounds min > max on axis {axis}"));
    }
    Ok(())
}

/// `u64 id, listing, pose`.
pub(super) fn put_scan_listed(
    out: &mut Vec<u8>,
    id: ScanId,
    listing: &ScanListing,
    world_from_scan: &Pose,
) -> Result<(), WireError> {
    check_listing(listing).map_err(|m| WireError::encode("ScanListed.listing", m))?;
    out.put_u64(id);
    out.put_u64(listing.timestamp_ns);
    for v in listing
        .bounds_min_m
        .iter()
        .chain(&listing.bounds_max_m)
        .chain(&listing.cop_m)
    {
        out.put_f32(*v);
    }
    out.put_f32(listing.priority);
    out.put_u64(listing.encoded_bytes);
    put_pose(out, "ScanListed.world_from_scan", world_from_scan)
}

pub(super) fn read_scan_listed(body: &[u8]) -> Result<(ScanId, ScanListing, Pose), WireError> {
    let mut r = BodyReader::new(body, "ScanListed");
    let id = r.u64("id")?;
    let timestamp_ns = r.u64("timestamp_ns")?;
    let mut v = [0f32; 9];
    for x in &mut v {
        *x = r.f32("bounds and centre")?;
    }
    let priority = r.f32("priority")?;
    let encoded_bytes = r.u64("encoded_bytes")?;
    let world_from_scan = read_pose(&mut r, "world_from_scan")?;
    r.finish()?;
    let listing = ScanListing {
        timestamp_ns,
        bounds_min_m: [v[0], v[1], v[2]],
        bounds_max_m: [v[3], v[4], v[5]],
        cop_m: [v[6], v[7], v[8]],
        priority,
        encoded_bytes,
    };
    check_listing(&listing).map_err(|m| WireError::invalid("ScanListed", m))?;
    Ok((id, listing, world_from_scan))
}

/// A message that is a scan id alone (`ScanWithdrawn`, `RequestScan`).
pub(super) fn read_id(body: &[u8], what: &'static str) -> Result<ScanId, WireError> {
    let mut r = BodyReader::new(body, what);
    let id = r.u64("id")?;
    r.finish()?;
    Ok(id)
}

/// `u64 id, string reason`.
pub(super) fn put_unavailable(
    out: &mut Vec<u8>,
    id: ScanId,
    reason: &str,
) -> Result<(), WireError> {
    out.put_u64(id);
    put_string(out, "ScanUnavailable.reason", reason, MAX_REASON_LEN)
}

pub(super) fn read_unavailable(body: &[u8]) -> Result<(ScanId, String), WireError> {
    let mut r = BodyReader::new(body, "ScanUnavailable");
    let id = r.u64("id")?;
    let reason = r.string("reason", MAX_REASON_LEN)?;
    r.finish()?;
    Ok((id, reason))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::super::{Limits, Message, decode_frame};
    use super::*;

    fn listing() -> ScanListing {
        ScanListing {
            timestamp_ns: 5,
            bounds_min_m: [-1.0, -2.0, 0.5],
            bounds_max_m: [1.0, 2.0, 4.0],
            cop_m: [0.0, 0.0, 0.0],
            priority: 0.25,
            encoded_bytes: 1_500_000,
        }
    }

    #[test]
    fn a_listing_is_its_documented_length_and_round_trips() {
        let m = Message::ScanListed {
            id: 9,
            listing: listing(),
            world_from_scan: Pose::translation(5e6, 1.0, -3.0),
        };
        let bytes = m.encode().unwrap();
        // Prefix, kind, id, listing, pose.
        assert_eq!(bytes.len(), 4 + 1 + 8 + LISTING_LEN + 7 * 8);
        let (back, used) = decode_frame(&bytes, &Limits::FROM_SERVER).unwrap().unwrap();
        assert_eq!((back, used), (m, bytes.len()));
    }

    #[test]
    fn inverted_or_non_finite_listings_neither_encode_nor_decode() {
        let good = Message::ScanListed {
            id: 1,
            listing: listing(),
            world_from_scan: Pose::identity(),
        }
        .encode()
        .unwrap();
        // Byte offsets in the frame: prefix 4, kind 1, id 8, timestamp 8.
        let floats_at = 4 + 1 + 8 + 8;
        for (float, value) in [(0, f32::NAN), (3, -5.0), (8, f32::INFINITY), (9, f32::NAN)] {
            let mut bytes = good.clone();
            let at = floats_at + 4 * float;
            bytes[at..at + 4].copy_from_slice(&value.to_le_bytes());
            let r = decode_frame(&bytes, &Limits::FROM_SERVER);
            assert!(
                matches!(r, Err(WireError::Invalid { .. })),
                "{float}: {r:?}"
            );
        }
        let mut inverted = listing();
        inverted.bounds_min_m[2] = 9.0;
        let m = Message::ScanListed {
            id: 1,
            listing: inverted,
            world_from_scan: Pose::identity(),
        };
        assert!(matches!(m.encode(), Err(WireError::Encode { .. })));
    }
}
