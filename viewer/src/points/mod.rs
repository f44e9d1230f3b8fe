//! The point proxy of Lechelek et al. (2019) on the CPU, the reference a GPU `points`
//! mode is tested against: splatting into per-view depth maps with front/back
//! classification and pull-push (`splat`, `pull_push`), and the weighting of the
//! acquisition views' pixels (`blend`).

pub mod blend;
pub mod cloud;
pub mod pull_push;
pub mod splat;
