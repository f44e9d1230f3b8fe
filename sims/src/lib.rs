//! The simulated texel camera: scenes, ray casting, effects, trajectories, ground
//! truth, and captures.
//!
//! A [`Scene`] (TOML, `configs/scenes/`) names a sensor file, the effects to simulate,
//! a trajectory, materials, objects and lights. A [`Simulator`] renders its frames:
//! frame `i` is a pure function of (scene, options, seed, `i`), bit-identical whatever
//! the thread count or the order frames are asked for in. Only the effects the scene
//! lists run (see [`effects`]); with none, every range is the exact radial distance
//! along the pixel's ray and the EO image is the clean render.
//!
//! # API
//!
//! ```no_run
//! use std::path::Path;
//! use sims::{Scene, SimOptions, Simulator};
//!
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let scene = Scene::load(Path::new("configs/scenes/lab.toml"))?;
//! // Replace the effect list, resolution or frame count without editing files:
//! let options = SimOptions { seed: 7, effects: Some(vec![]), frames: Some(3), ..SimOptions::default() };
//! let sim = Simulator::with_options(scene, &options)?;
//! let frame = sim.frame(0)?;                      // SimFrame { pair, world_from_eo, .. }
//! let truth = sim.lidar_truth(0);                 // true world point per lidar pixel
//! let model = sim.sensor_model();                 // the calibration the frames match
//! let view = sim.scene().render_view(&frame.world_from_eo, &model.eo); // clean EO image
//! sims::render_capture(&sim, Path::new("out.mcap"), &Default::default(), &mut |_, _| {})?;
//! # Ok(()) }
//! ```
//!
//! - [`Scene::load`], [`Scene::from_toml_str`]: parse and validate; errors
//!   ([`SceneError`]) name the file, line and key.
//! - [`Scene::sensor`], [`Scene::frame_count`], [`Scene::frame_rate_hz`],
//!   [`Scene::cast_ray`] (f64 ground truth: distance, point, normal, object id),
//!   [`Scene::render_view`] (clean EO image from any pose through any camera).
//! - [`Simulator::new`], [`Simulator::with_options`] ([`SimOptions`]: seed, effect
//!   list, frames, lidar/EO resolution, backend), [`Simulator::frame`],
//!   [`Simulator::frame_count`], [`Simulator::frame_rate_hz`],
//!   [`Simulator::true_pose`], [`Simulator::sensor_model`] / [`Simulator::sensor`]
//!   (the model frames are rendered with and captures carry).
//! - Any pose: [`Simulator::render_at`], [`Simulator::range_at`],
//!   [`Simulator::clean_range_at`], [`Simulator::clean_eo_at`],
//!   [`Simulator::echoes_at`], [`Simulator::lidar_truth_at`].
//! - [`render_capture`]: a capture (`docs/capture-format.md`) with a progress callback.
//!
//! # Lens distortion and calibration
//!
//! The capture always carries the camera model its pixels were formed with. Under the
//! `lens_distortion` effect both cameras use the sensor file's `plumb_bob`
//! coefficients; without it both are ideal pinholes with the same `K` and the capture
//! says so. Fusing any capture with the calibration it carries is therefore exact.
//!
//! # Backends
//!
//! The clean signal (echoes, radiance) comes from a [`render::RenderBackend`]: the
//! built-in ray caster, or Mitsuba 3 ([`render::mitsuba`], a Python process in the
//! venv `scripts/setup.sh` makes) traced along the same per-pixel rays. `SimOptions::
//! backend` is [`BackendKind::Auto`] by default: built-in, unless an effect only
//! Mitsuba simulates (`global_illumination`) is asked for. Effects are applied by the
//! same pipelines whatever the backend; a backend that fails while rendering makes
//! [`Simulator::frame`] return [`SimError::Backend`].
//!
//! # Virtual serial lidar
//!
//! [`serial::VirtualLidar`] writes a simulation's range frames as TXL1 to any `Write`,
//! with injected faults and an exact [`serial::InjectionLog`]; [`serial::spawn_pty`]
//! runs it on a pseudo-terminal a reader opens like a real port;
//! [`serial::sim_frame_for_seq`] gives the texel frame (with its EO image) of a seq.

pub mod capture;
pub mod effects;
pub mod geometry;
pub mod light;
pub mod material;
pub mod noise;
pub mod render;
pub mod rng;
pub mod scene;
pub mod serial;
pub mod simulator;
pub mod texture_gen;
pub mod trajectory;
pub mod world;

pub use capture::{CaptureOptions, CaptureSummary, render_capture};
pub use effects::{Effect, EffectSet};
pub use render::BackendKind;
pub use scene::{ObjectInfo, Scene, SceneError};
pub use simulator::{LidarTruth, SimError, SimFrame, SimOptions, Simulator, rescale_camera};
pub use world::TruthHit;
