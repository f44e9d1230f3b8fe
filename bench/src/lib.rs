//! Texel's tooling, in the `cargo xtask` manner: benchmarks of the daemon and the
//! viewer, the reports that regenerate `docs/tradeoffs.md` (what accuracy costs in
//! time, measured against the simulator's truth), and calibration measured against
//! the simulator. Product crates never depend on this one.

// Negated comparisons (`!(x < limit)`) are deliberate: a NaN takes the rejecting
// branch with them.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod calibration;
pub mod capture_read;
pub mod daemon_capture;
pub mod daemon_sim;
pub mod live_viewer;
pub mod long_session;
pub mod replay_memory;
pub mod tradeoffs;
pub mod txl1_decode;
pub mod viewer_bench;
pub mod web_viewer;
