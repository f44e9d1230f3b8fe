//! The `points` mode on the GPU (Lechelek et al. 2019, the point proxy; the CPU
//! reference is `crate::points`): the pipelines (`pipelines.rs`), per-view depth maps
//! by splatting and pull-push (`depth_map.rs`), each scan's points and acquisition
//! depth map (`scan.rs`), and the frame: the virtual view's depth map, each visible
//! scan's weighted colour accumulated, the weighted mean into the target.

pub(crate) mod depth_map;
pub(crate) mod pipelines;
pub(crate) mod scan;

pub use depth_map::pyramid;
pub use pipelines::{POINT_ACCUMULATION_FORMAT, POINT_DEPTH_FORMAT, POINT_NORMAL_FORMAT};
pub use scan::{MAX_ACQUISITION_MAP_PX, acquisition_map_size};
