//! The fields of the version 3 messages of the level-of-detail tree
//! (`docs/wire-protocol.md`, "Tiles"): a tile's listing, its withdrawal, a client's
//! request for its data, the data and the answer that a request cannot be met. Tile
//! data is opaque here (the `TXLT` bytes of `texel-lod`'s codec, which checks them);
//! the frame bounds its length before anything is allocated.

use super::bytes_in::{BodyReader, PutLe};
use super::{MAX_REASON_LEN, WireError, put_string};
use crate::tile::{MAX_LOD, TileId, TileListing};

/// The largest tile data a frame carries. A tile is simplified to a triangle budget
/// (16,384 by default, about 40 kB encoded); this leaves room for budgets far larger.
pub const MAX_TILE_DATA_BYTES: usize = 64 * 1024 * 1024;

/// Bytes of a tile id on the wire: lod u8, x i64, y i64.
pub const TILE_ID_LEN: usize = 1 + 8 + 8;

/// Bytes of a `TileListed` body after its kind: id, revision, 6 f64 bounds, error,
/// triangles, encoded size.
pub const TILE_LISTED_LEN: usize = TILE_ID_LEN + 8 + 6 * 8 + 8 + 4 + 8;

/// A tile's data: the answer to a `RequestTile`.
#[derive(Debug, Clone, PartialEq)]
pub struct WireTile {
    pub id: TileId,
    /// The revision the data is of (as listed when it was made).
    pub revision: u64,
    /// The tile in `texel-lod`'s compact encoding (`TXLT`).
    pub data: Vec<u8>,
}

pub(super) fn put_tile_id(out: &mut Vec<u8>, id: TileId) {
    out.put_u8(id.lod);
    out.put_u64(id.x as u64);
    out.put_u64(id.y as u64);
}

pub(super) fn read_tile_id(r: &mut BodyReader<'_>) -> Result<TileId, WireError> {
    let lod = r.u8("tile lod")?;
    let x = r.u64("tile x")? as i64;
    let y = r.u64("tile y")? as i64;
    if lod > MAX_LOD {
        return Err(WireError::invalid(
            "tile id",
            format!("level {lod} is above the highest level {MAX_LOD}"),
        ));
    }
    Ok(TileId { lod, x, y })
}

pub(super) fn put_tile_listed(
    out: &mut Vec<u8>,
    id: TileId,
    listing: &TileListing,
) -> Result<(), WireError> {
    listing
        .check()
        .map_err(|m| WireError::encode("TileListed.listing", m))?;
    if id.lod > MAX_LOD {
        return Err(WireError::encode(
            "TileListed.id",
            format!("level {} is above {MAX_LOD}", id.lod),
        ));
    }
    put_tile_id(out, id);
    out.put_u64(listing.revision);
    for v in listing.bounds_min_m.iter().chain(&listing.bounds_max_m) {
        out.put_f64(*v);
    }
    out.put_f64(listing.geometric_error_m);
    out.put_u32(listing.triangles);
    out.put_u64(listing.encoded_bytes);
    Ok(())
}

pub(super) fn read_tile_listed(body: &[u8]) -> Result<(TileId, TileListing), WireError> {
    let mut r = BodyReader::new(body, "TileListed");
    let id = read_tile_id(&mut r)?;
    let revision = r.u64("revision")?;
    let mut v = [0f64; 6];
    for x in &mut v {
        *x = r.f64("bounds")?;
    }
    let geometric_error_m = r.f64("geometric_error_m")?;
    let triangles = r.u32("triangles")?;
    let encoded_bytes = r.u64("encoded_bytes")?;
    r.finish()?;
    let listing = TileListing {
        revision,
        bounds_min_m: [v[0], v[1], v[2]],
        bounds_max_m: [v[3], v[4], v[5]],
        geometric_error_m,
        triangles,
        encoded_bytes,
    };
    listing
        .check()
        .map_err(|m| WireError::invalid("TileListed", m))?;
    Ok((id, listing))
}

/// A message that is a tile id alone (`TileWithdrawn`, `RequestTile`).
pub(super) fn read_tile_only(body: &[u8], what: &'static str) -> Result<TileId, WireError> {
    let mut r = BodyReader::new(body, what);
    let id = read_tile_id(&mut r)?;
    r.finish()?;
    Ok(id)
}

pub(super) fn put_tile_data(out: &mut Vec<u8>, tile: &WireTile) -> Result<(), WireError> {
    if tile.data.len() > MAX_TILE_DATA_BYTES {
        return Err(WireError::encode(
            "TileData.data",
            format!(
                "{} bytes exceed the limit {MAX_TILE_DATA_BYTES}",
                tile.data.len()
            ),
        ));
    }
    put_tile_id(out, tile.id);
    out.put_u64(tile.revision);
    out.put_bytes(&tile.data);
    Ok(())
}

pub(super) fn read_tile_data(body: &[u8]) -> Result<WireTile, WireError> {
    let mut r = BodyReader::new(body, "TileData");
    let id = read_tile_id(&mut r)?;
    let revision = r.u64("revision")?;
    let n = r.count("data", 1, MAX_TILE_DATA_BYTES)?;
    let data = r.take(n, "data")?.to_vec();
    r.finish()?;
    Ok(WireTile { id, revision, data })
}

pub(super) fn put_tile_unavailable(
    out: &mut Vec<u8>,
    id: TileId,
    reason: &str,
) -> Result<(), WireError> {
    put_tile_id(out, id);
    put_string(out, "TileUnavailable.reason", reason, MAX_REASON_LEN)
}

pub(super) fn read_tile_unavailable(body: &[u8]) -> Result<(TileId, String), WireError> {
    let mut r = BodyReader::new(body, "TileUnavailable");
    let id = read_tile_id(&mut r)?;
    let reason = r.string("reason", MAX_REASON_LEN)?;
    r.finish()?;
    Ok((id, reason))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::super::{Limits, Message, decode_frame};
    use super::*;

    fn listing() -> TileListing {
        TileListing {
            revision: 17,
            bounds_min_m: [-12.8, 25.6, -0.5],
            bounds_max_m: [0.0, 38.4, 14.0],
            geometric_error_m: 0.12,
            triangles: 16_000,
            encoded_bytes: 41_000,
        }
    }

    fn id() -> TileId {
        TileId {
            lod: 3,
            x: -7,
            y: 1 << 40,
        }
    }

    #[test]
    fn tile_messages_are_their_documented_length_and_round_trip() {
        let listed = Message::TileListed {
            id: id(),
            listing: listing(),
        };
        let bytes = listed.encode().unwrap();
        assert_eq!(bytes.len(), 4 + 1 + TILE_LISTED_LEN);
        for m in [
            listed,
            Message::TileWithdrawn { id: id() },
            Message::RequestTile { id: id() },
            Message::TileUnavailable {
                id: id(),
                reason: "tile 3/-7/1099511627776 is not in the tree".into(),
            },
            Message::TileData(Box::new(WireTile {
                id: id(),
                revision: 17,
                data: b"TXLT and more".to_vec(),
            })),
        ] {
            let bytes = m.encode().unwrap();
            let (back, used) = decode_frame(&bytes, &Limits::FROM_SERVER).unwrap().unwrap();
            assert_eq!((&back, used), (&m, bytes.len()), "{}", m.kind_name());
            // Every prefix is "read more", never a message or an error.
            for cut in 0..bytes.len() {
                assert_eq!(decode_frame(&bytes[..cut], &Limits::FROM_SERVER), Ok(None));
            }
        }
    }

    #[test]
    fn bad_listings_ids_and_lengths_are_refused_naming_the_field() {
        let good = Message::TileListed {
            id: id(),
            listing: listing(),
        }
        .encode()
        .unwrap();
        // Offsets: prefix 4, kind 1, id 17, revision 8, then the f64s.
        let floats_at = 4 + 1 + TILE_ID_LEN + 8;
        for (float, value) in [(0, f64::NAN), (4, -1e9), (6, -0.5), (6, f64::INFINITY)] {
            let mut bytes = good.clone();
            let at = floats_at + 8 * float;
            bytes[at..at + 8].copy_from_slice(&value.to_le_bytes());
            let r = decode_frame(&bytes, &Limits::FROM_SERVER);
            assert!(
                matches!(r, Err(WireError::Invalid { .. })),
                "{float}: {r:?}"
            );
        }
        let mut high = good.clone();
        high[5] = MAX_LOD + 1;
        let e = decode_frame(&high, &Limits::FROM_SERVER).unwrap_err();
        assert!(e.to_string().contains("above the highest level"), "{e}");
        // A data length beyond the bytes present is invalid once the frame is whole.
        let mut data = Message::TileData(Box::new(WireTile {
            id: id(),
            revision: 1,
            data: vec![7; 10],
        }))
        .encode()
        .unwrap();
        let len_at = 4 + 1 + TILE_ID_LEN + 8;
        data[len_at..len_at + 4].copy_from_slice(&11u32.to_le_bytes());
        let e = decode_frame(&data, &Limits::FROM_SERVER).unwrap_err();
        assert!(e.to_string().contains("data"), "{e}");
        let mut inverted = listing();
        inverted.bounds_min_m[0] = 5.0;
        let m = Message::TileListed {
            id: id(),
            listing: inverted,
        };
        assert!(matches!(m.encode(), Err(WireError::Encode { .. })));
    }
}
