//! The texel model viewer: the view-dependent wgpu renderer (Killpack & Budge 2016),
//! its CPU reference, capture loading, headless rendering and the window.

pub mod camera;
pub mod composite;
pub mod cull;
pub mod gpu;
pub mod reliability;
pub mod scenes;
