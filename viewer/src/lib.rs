//! The texel model viewer: the view-dependent wgpu renderer (Killpack & Budge 2016),
//! its CPU reference, capture loading, headless rendering, the window and the browser
//! page (`web`, built for wasm32).

pub mod adaptive;
pub mod app;
pub mod camera;
pub mod capture_load;
pub mod composite;
pub mod cull;
pub mod deep_link;
pub mod display_mode;
pub mod footprint;
pub mod gpu;
pub mod headless;
pub mod live;
pub mod points;
pub mod reliability;
pub mod residency;
pub mod scenes;
pub mod tiles;
pub mod tonemap;
pub mod vdtm;
pub mod web;
#[cfg(not(target_arch = "wasm32"))]
pub mod zenoh_source;
