//! A client's view of the daemon's level-of-detail tree (version 3): every listed
//! tile, the data of those it fetched, and which requests are unanswered. It decides
//! nothing about what to draw: a viewer selects tiles by screen-space error
//! (`texel-lod`'s `select`) and asks the catalog for the ones it wants.

use std::collections::{BTreeMap, BTreeSet};

use super::WireTile;
use crate::tile::{TileId, TileListing};

/// A change to the tree, decoded from a server message.
#[derive(Debug, Clone, PartialEq)]
pub enum TileEvent {
    Listed { id: TileId, listing: TileListing },
    Withdrawn { id: TileId },
    Data(Box<WireTile>),
    Unavailable { id: TileId, reason: String },
}

/// The listed tiles and the fetched data.
#[derive(Debug, Clone, Default)]
pub struct TileCatalog {
    listings: BTreeMap<TileId, TileListing>,
    data: BTreeMap<TileId, WireTile>,
    requested: BTreeSet<TileId>,
    /// Tiles the server said it cannot send, until they are listed again.
    unavailable: BTreeSet<TileId>,
    bytes_received: u64,
}

impl TileCatalog {
    pub fn new() -> Self {
        Self::default()
    }

    /// Forgets everything (a `ModelReset`).
    pub fn clear(&mut self) {
        *self = Self {
            bytes_received: self.bytes_received,
            ..Self::default()
        };
    }

    /// Applies one change.
    pub fn apply(&mut self, event: TileEvent) {
        match event {
            TileEvent::Listed { id, listing } => {
                self.unavailable.remove(&id);
                self.listings.insert(id, listing);
            }
            TileEvent::Withdrawn { id } => {
                self.listings.remove(&id);
                self.data.remove(&id);
                self.requested.remove(&id);
                self.unavailable.remove(&id);
            }
            TileEvent::Data(tile) => {
                self.requested.remove(&tile.id);
                self.bytes_received += tile.data.len() as u64;
                // Data of a tile no longer listed (withdrawn while in flight) is not kept.
                if self.listings.contains_key(&tile.id) {
                    self.data.insert(tile.id, *tile);
                }
            }
            TileEvent::Unavailable { id, .. } => {
                self.requested.remove(&id);
                self.unavailable.insert(id);
            }
        }
    }

    pub fn listing(&self, id: TileId) -> Option<&TileListing> {
        self.listings.get(&id)
    }

    /// Every listed tile.
    pub fn listings(&self) -> impl Iterator<Item = (TileId, &TileListing)> + '_ {
        self.listings.iter().map(|(id, l)| (*id, l))
    }

    pub fn len(&self) -> usize {
        self.listings.len()
    }

    pub fn is_empty(&self) -> bool {
        self.listings.is_empty()
    }

    /// The listed tiles whose parent is not listed: the top of the tree.
    pub fn roots(&self) -> Vec<TileId> {
        self.listings
            .keys()
            .filter(|id| id.parent().is_none_or(|p| !self.listings.contains_key(&p)))
            .copied()
            .collect()
    }

    /// The held data of a tile, whatever its revision.
    pub fn data(&self, id: TileId) -> Option<&WireTile> {
        self.data.get(&id)
    }

    /// Whether the held data is of the listed revision.
    pub fn is_current(&self, id: TileId) -> bool {
        match (self.listings.get(&id), self.data.get(&id)) {
            (Some(l), Some(d)) => d.revision == l.revision,
            _ => false,
        }
    }

    /// Of `wanted` (most needed first), the tiles to request now, counted as
    /// requested: listed, not current, not in flight, not unavailable, keeping at most
    /// `max_in_flight` unanswered in all.
    pub fn request(
        &mut self,
        wanted: impl IntoIterator<Item = TileId>,
        max_in_flight: usize,
    ) -> Vec<TileId> {
        let mut out = Vec::new();
        for id in wanted {
            if self.requested.len() >= max_in_flight {
                break;
            }
            if self.listings.contains_key(&id)
                && !self.is_current(id)
                && !self.unavailable.contains(&id)
                && self.requested.insert(id)
            {
                out.push(id);
            }
        }
        out
    }

    /// Requests sent and not yet answered.
    pub fn in_flight(&self) -> usize {
        self.requested.len()
    }

    /// Tile data bytes received since the catalog was made.
    pub fn bytes_received(&self) -> u64 {
        self.bytes_received
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;

    fn listing(revision: u64) -> TileListing {
        TileListing {
            revision,
            bounds_min_m: [0.0; 3],
            bounds_max_m: [1.0; 3],
            geometric_error_m: 0.1,
            triangles: 2,
            encoded_bytes: 10,
        }
    }

    fn tile(lod: u8, x: i64, y: i64) -> TileId {
        TileId { lod, x, y }
    }

    #[test]
    fn a_catalog_fetches_what_is_not_current_and_refetches_a_rebuilt_tile() {
        let mut c = TileCatalog::new();
        let top = tile(1, 0, 0);
        let child = tile(0, 1, 0);
        c.apply(TileEvent::Listed {
            id: top,
            listing: listing(1),
        });
        c.apply(TileEvent::Listed {
            id: child,
            listing: listing(2),
        });
        assert_eq!(c.roots(), vec![top]);
        // Unlisted tiles are never requested; the budget holds.
        assert_eq!(c.request([tile(0, 5, 5), top, child], 1), vec![top]);
        assert_eq!(c.request([top, child], 1), Vec::<TileId>::new());
        c.apply(TileEvent::Data(Box::new(WireTile {
            id: top,
            revision: 1,
            data: vec![1, 2, 3],
        })));
        assert!(c.is_current(top));
        assert_eq!(c.request([top, child], 4), vec![child]);
        // A rebuild makes the held data stale: fetched again.
        c.apply(TileEvent::Listed {
            id: top,
            listing: listing(3),
        });
        assert!(!c.is_current(top) && c.data(top).is_some());
        assert_eq!(c.request([top], 4), vec![top]);
        // Unavailable: not asked again until listed again.
        c.apply(TileEvent::Unavailable {
            id: child,
            reason: "gone".into(),
        });
        assert_eq!(c.request([child], 4), Vec::<TileId>::new());
        // A withdrawal forgets the tile and its request; late data is not kept.
        c.apply(TileEvent::Withdrawn { id: top });
        assert_eq!(c.in_flight(), 0);
        c.apply(TileEvent::Data(Box::new(WireTile {
            id: top,
            revision: 3,
            data: vec![4],
        })));
        assert!(c.data(top).is_none());
        assert_eq!(c.bytes_received(), 4);
        assert_eq!(c.roots(), vec![child]);
    }
}
