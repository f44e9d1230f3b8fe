//! Where tile bytes come from: the [`TileSource`] trait (a listing of the tiles with
//! their revision, bounds and error, and encoded bytes on request, answered now or
//! frames later), and [`MemorySource`], over a `texel_lod::Hierarchy` held in memory
//! (for tests and for a capture built locally). The network source (the daemon lists
//! tiles and sends encoded bytes on request) implements the same trait.

use std::collections::{BTreeMap, VecDeque};

use texel_lod::{Hierarchy, LodNode, TileId, TileInfo, encode_tile};

/// A tile as a source lists it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TileEntry {
    pub id: TileId,
    /// Grows each time the tile is rebuilt.
    pub revision: u64,
    /// Bounds and geometric error, for selection.
    pub info: TileInfo,
}

impl TileEntry {
    pub fn of(node: &LodNode, revision: u64) -> Self {
        Self {
            id: node.id,
            revision,
            info: TileInfo {
                bounds_min_m: node.bounds_min_m,
                bounds_max_m: node.bounds_max_m,
                geometric_error_m: node.geometric_error_m,
            },
        }
    }
}

/// A tile's bytes as `texel_lod::encode_tile` made them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EncodedTile {
    pub id: TileId,
    pub revision: u64,
    pub bytes: Vec<u8>,
}

/// A tile that could not be had: fetching or decoding it failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("tile {}: {message}", id.path())]
pub struct LoadError {
    pub id: TileId,
    pub message: String,
}

/// Where tiles come from. Called from the render thread only; every call returns at
/// once (a slow source answers requests from `receive` frames later).
pub trait TileSource {
    /// The whole listing, when it changed since the last call (the first call
    /// always returns it).
    fn poll_listing(&mut self) -> Option<Vec<TileEntry>>;
    /// Asks for a tile's bytes (its current revision).
    fn request(&mut self, id: TileId);
    /// What arrived since the last call: bytes, or failed requests.
    fn receive(&mut self) -> Vec<Result<EncodedTile, LoadError>>;
}

/// Tiles held in memory, encoded with `encode_tile`, each answered `delay_receives`
/// calls of `receive` after its request (0: in the same frame).
#[derive(Debug, Clone, Default)]
pub struct MemorySource {
    tiles: BTreeMap<TileId, (TileEntry, Vec<u8>)>,
    pending: VecDeque<(u32, TileId)>,
    delay_receives: u32,
    listing_changed: bool,
    requests: u64,
}

impl MemorySource {
    /// Every tile of the hierarchy, revision 1.
    pub fn new(hierarchy: &Hierarchy) -> Self {
        Self::from_nodes(hierarchy.nodes.values())
    }

    /// The given tiles only, revision 1 (e.g. only the finest level, for a render
    /// at full detail: the listing's top level is then the finest).
    pub fn from_nodes<'a>(nodes: impl IntoIterator<Item = &'a LodNode>) -> Self {
        let tiles = nodes
            .into_iter()
            .map(|n| (n.id, (TileEntry::of(n, 1), encode_tile(n))))
            .collect();
        Self {
            tiles,
            listing_changed: true,
            ..Self::default()
        }
    }

    /// Answers each request `receives` calls of `receive` after it.
    pub fn with_delay(mut self, receives: u32) -> Self {
        self.delay_receives = receives;
        self
    }

    /// A rebuilt tile: its bytes replaced and its revision raised (added if new).
    pub fn replace(&mut self, node: &LodNode) -> u64 {
        let revision = self.tiles.get(&node.id).map_or(1, |(e, _)| e.revision + 1);
        self.tiles
            .insert(node.id, (TileEntry::of(node, revision), encode_tile(node)));
        self.listing_changed = true;
        revision
    }

    /// Replaces a listed tile's bytes as they are (e.g. corrupt ones), keeping its
    /// revision. False if the tile is not listed.
    pub fn set_bytes(&mut self, id: TileId, bytes: Vec<u8>) -> bool {
        match self.tiles.get_mut(&id) {
            Some((_, b)) => {
                *b = bytes;
                true
            }
            None => false,
        }
    }

    /// Requests received so far.
    pub fn requests(&self) -> u64 {
        self.requests
    }

    pub fn len(&self) -> usize {
        self.tiles.len()
    }

    pub fn is_empty(&self) -> bool {
        self.tiles.is_empty()
    }
}

impl TileSource for MemorySource {
    fn poll_listing(&mut self) -> Option<Vec<TileEntry>> {
        if !std::mem::take(&mut self.listing_changed) {
            return None;
        }
        Some(self.tiles.values().map(|(e, _)| *e).collect())
    }

    fn request(&mut self, id: TileId) {
        self.requests += 1;
        self.pending.push_back((self.delay_receives, id));
    }

    fn receive(&mut self) -> Vec<Result<EncodedTile, LoadError>> {
        let mut out = Vec::new();
        let mut waiting = VecDeque::new();
        for (left, id) in self.pending.drain(..) {
            if left > 0 {
                waiting.push_back((left - 1, id));
                continue;
            }
            out.push(match self.tiles.get(&id) {
                Some((entry, bytes)) => Ok(EncodedTile {
                    id,
                    revision: entry.revision,
                    bytes: bytes.clone(),
                }),
                None => Err(LoadError {
                    id,
                    message: "not in the listing".into(),
                }),
            });
        }
        self.pending = waiting;
        out
    }
}
