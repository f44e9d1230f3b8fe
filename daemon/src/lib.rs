//! The Texel daemon's library: sources, the pipeline (sync, fusion, the registration
//! stage, the model), recording, the viewer stream server, status and
//! configuration; plus the capture tools behind `texeld info` and `texeld export`.

pub mod cli;
pub mod config;
pub mod export;
#[cfg(feature = "foxglove-live")]
pub mod foxglove_live;
pub mod hub;
pub mod info;
pub mod model_export;
pub mod pages;
pub mod pipeline;
pub mod record;
pub mod register_cli;
pub mod resume;
pub mod serve_order;
pub mod server;
pub mod shelf;
pub mod source;
pub mod status;
pub mod store;
pub mod texture;
pub mod tiles_export;
pub mod zenoh_publish;
