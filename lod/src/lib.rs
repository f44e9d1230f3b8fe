//! Hierarchical level of detail for the texel model (Liu 2014): a quadtree over the
//! ground whose tiles hold the merged surface of the scans under them, simplified to
//! one triangle budget per tile; selection of the tiles to draw by screen-space error;
//! and the hierarchy as an OGC 3D Tiles 1.1 tileset. Pure, synchronous, I/O-free.

pub mod atlas;
pub mod build;
pub mod codec;
pub mod fields;
pub mod merged;
pub mod model;
pub mod select;
pub mod tiles;
mod tiles_meshopt;
pub mod tree;

pub use atlas::TileTexture;
pub use build::{Hierarchy, LodConfig, LodError, LodNode, build_from_field};
pub use codec::{TileCodecError, atlas_png, decode_tile, encode_tile};
pub use fields::PagingCounts;
pub use merged::{merged_surface, whole_surface_config};
pub use model::LodModel;
pub use select::{Lens, SelectConfig, Selection, TileIndex, TileInfo, View, select};
pub use tiles::{GeoReference, TileCompression, TileFile, TilesError, tileset_files};
pub use tree::{Grid, MAX_LOD, TileId};
