//! View-dependent texture mapping as a viewer mode (Debevec, Yu & Borshukov 1998):
//! `prepare.rs` builds the merged surface and runs `texel-vdtm`'s preprocessing on
//! the model, `gpu.rs` uploads the result (polygons in draw order, the images as one
//! texture array, each view's camera), `pass.rs` draws it into a given target and
//! `live.rs` keeps it up to date with a growing model on a worker thread.

pub mod gpu;
pub mod live;
pub mod pass;
pub mod prepare;

pub use gpu::{GpuVdtm, PolygonBlend, polygon_blend};
pub use live::{LiveVdtm, VdtmChoice, VdtmStatus};
pub use pass::{VdtmPass, VdtmSettings, render_vdtm_to_image};
pub use prepare::{PrepareError, PreparedVdtm, PreparedView, VdtmViewConfig, prepare};
