//! View-dependent texture mapping on the merged surface (Debevec, Yu & Borshukov
//! 1998): per polygon, which acquisition views see it and, for any viewing direction,
//! which of them (at most three) texture it with which weights. Pure and I/O-free:
//! the viewer renders with what it computes. One module per step of the paper:
//! `view_map.rs` (§7, the per-polygon view maps).

pub mod view_map;

pub use view_map::{Blend, PolygonFrame, ViewMap, ViewMapError};
