//! The Pareto plots of the tradeoffs sections come from the shared chart crate.

pub use texel_plots::{Series, pareto_front, write_pareto};
