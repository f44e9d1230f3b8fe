//! View-dependent texture mapping on the merged surface (Debevec, Yu & Borshukov
//! 1998): per polygon, which acquisition views see it and, for any viewing direction,
//! which of them (at most three) texture it with which weights. Pure and I/O-free:
//! the viewer renders with what it computes. One module per step of the paper:
//! `view.rs` (the acquisition views), `visibility.rs` (§5, which views see which
//! polygons), `hole_fill.rs` (§6, colours for polygons no view sees), `view_map.rs`
//! (§7, the per-polygon view maps) and `model.rs` (the recipe, and §8's per-frame
//! query).

pub mod hole_fill;
pub mod model;
pub mod view;
pub mod view_map;
pub mod visibility;

pub use hole_fill::{
    HoleFill, HoleFillConfig, HoleFillError, HoleFillStats, fill_holes, triangle_colours,
    triangle_colours_where,
};
pub use model::{Texturing, VdtmConfig, VdtmError, VdtmModel, VdtmStats};
pub use view::AcquisitionView;
pub use view_map::{Blend, PolygonFrame, ViewMap, ViewMapError};
pub use visibility::{VisibilityConfig, VisibilityError, VisibilityStats, VisibleMesh, visibility};
