//! The merged surface of registered texel scans: every scan's returns fused into one
//! truncated signed distance field (TSDF), the zero crossing extracted as a coloured
//! triangle mesh (surface nets) and simplified to a triangle budget.
//!
//! Level of detail (Liu 2014) and view-dependent texture mapping (Debevec 1998) both
//! draw on this one surface. Pure, synchronous, I/O-free; world coordinates in f64,
//! meshes as f32 offsets from an f64 origin.

pub mod integrate;
pub mod mesh;
pub mod nets;
pub mod tsdf;

pub use integrate::{integrate_scan, remove_scan, scan_samples};
pub use mesh::{SimplifyOutcome, SurfaceMesh, simplify};
pub use nets::{VoxelRegion, extract};
pub use tsdf::{
    BLOCK_BYTES, BlockBytesError, BlockKey, Sample, Tsdf, TsdfConfig, TsdfError, VoxelIndex,
    parent_block,
};
