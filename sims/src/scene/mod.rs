//! Scenes: a TOML file naming the texel camera's sensor file, the effects to simulate,
//! a trajectory, materials, objects and lights (format reference:
//! `docs/simulator.md`). Loading validates everything and reports the file, line
//! and key of the first problem.

mod build;
mod file;

use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::{Point3, Vector3};
use texel::{EoFrame, PinholeCamera, Pose, SensorModel};

use crate::effects::{Effect, EffectSet};
use crate::geometry::Ray;
use crate::material::Rgb;
use crate::render::lidar::NoiseKey;
use crate::render::{BuiltinBackend, CameraRays, eo};
use crate::trajectory::Trajectory;
use crate::world::{TruthHit, World};

/// Largest lidar side (the TXL1 protocol's limit).
pub const MAX_LIDAR_SIDE: u32 = 1024;
/// Largest EO side.
pub const MAX_EO_SIDE: u32 = 8192;
/// Most frames a trajectory may have.
pub const MAX_FRAMES: u64 = 1_000_000;
/// Largest image texture side (pixels).
pub const MAX_TEXTURE_SIDE: u32 = 8192;
/// Most objects of a scene.
pub const MAX_OBJECTS: usize = 100_000;

/// A problem with a scene: where it is (file, line, key) and what is wrong.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneError {
    /// The scene file (or the name given to `from_toml_str`).
    pub origin: String,
    /// 1-based line in the scene file, when known.
    pub line: Option<usize>,
    /// Dotted key path (`objects.box[1].material`), or the TOML key on that line.
    pub key: String,
    pub message: String,
}

impl fmt::Display for SceneError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.origin)?;
        if let Some(line) = self.line {
            write!(f, ":{line}")?;
        }
        if !self.key.is_empty() {
            write!(f, ": {}", self.key)?;
        }
        write!(f, ": {}", self.message)
    }
}

impl std::error::Error for SceneError {}

/// What a scene object is, for reports and ground-truth queries.
#[derive(Debug, Clone, PartialEq)]
pub struct ObjectInfo {
    /// `plane`, `box`, `sphere`, `cylinder` or `mesh`.
    pub kind: &'static str,
    /// The object's `name`, or `kind[index]`.
    pub name: String,
}

/// A loaded scene.
#[derive(Debug, Clone)]
pub struct Scene {
    pub name: String,
    /// Where the scene came from (the file path).
    pub origin: String,
    sensor: SensorModel,
    /// The effects the scene calls for, in file order.
    pub effects: Vec<Effect>,
    pub trajectory: Trajectory,
    /// Objects in file order; `TruthHit::object` indexes this.
    pub objects: Vec<ObjectInfo>,
    pub(crate) world: Arc<World>,
}

impl Scene {
    /// Reads a scene file; its sensor, texture and mesh paths are relative to it.
    pub fn load(path: &Path) -> Result<Self, SceneError> {
        let origin = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| SceneError {
            origin: origin.clone(),
            line: None,
            key: String::new(),
            message: format!("cannot read the scene file: {e}"),
        })?;
        let base = path.parent().map_or_else(PathBuf::new, Path::to_path_buf);
        Self::from_toml_str(&text, &origin, &base)
    }

    /// Parses a scene's text; `origin` names it in errors and `base_dir` resolves its
    /// relative paths.
    pub fn from_toml_str(text: &str, origin: &str, base_dir: &Path) -> Result<Self, SceneError> {
        build::build(text, origin, base_dir)
    }

    /// The sensor model of the scene's sensor file (before the effects decide whether
    /// the lenses distort; see `Simulator::sensor_model` for the one frames are
    /// rendered with).
    pub fn sensor(&self) -> &SensorModel {
        &self.sensor
    }

    /// Replaces the sensor model (tests, calibration studies).
    pub fn set_sensor(&mut self, sensor: SensorModel) {
        self.sensor = sensor;
    }

    pub fn frame_count(&self) -> usize {
        self.trajectory.frames
    }

    pub fn frame_rate_hz(&self) -> f64 {
        self.trajectory.rate_hz
    }

    /// The effects of the scene as one set per stage.
    pub fn effect_set(&self) -> EffectSet {
        // Duplicates are refused at load time.
        EffectSet::from_list(&self.effects).unwrap_or_default()
    }

    /// Ground truth: the surface a ray from `origin` along `dir` (world coordinates,
    /// any non-zero length) meets first.
    pub fn cast_ray(&self, origin: Point3<f64>, dir: Vector3<f64>) -> Option<TruthHit> {
        let n = dir.norm();
        if !(n > 0.0 && n.is_finite() && origin.coords.iter().all(|c| c.is_finite())) {
            return None;
        }
        self.world.truth(&Ray {
            origin,
            dir: dir / n,
        })
    }

    /// A clean EO image (no effects) of the scene from any pose (`world_from_eo`,
    /// optical frame x right, y down, z forward) through any camera model.
    pub fn render_view(&self, world_from_eo: &Pose, camera: &PinholeCamera) -> EoFrame {
        let rays = CameraRays::new(camera);
        self.render_view_with(world_from_eo, &rays)
    }

    /// [`Self::render_view`] with the camera's rays computed once by the caller.
    pub fn render_view_with(&self, world_from_eo: &Pose, rays: &CameraRays) -> EoFrame {
        let linear = self.radiance_view_with(world_from_eo, rays);
        let effects = EffectSet::default();
        eo::develop(&linear, rays, &effects, NoiseKey { seed: 0, frame: 0 }, 0)
    }

    /// The linear radiance (row-major, in the units where 1.0 is white at 0 EV) the
    /// scene sends into each pixel of a camera at any pose: the truth a
    /// high-dynamic-range result is scored against, before any exposure, saturation or
    /// response curve.
    pub fn radiance_view(&self, world_from_eo: &Pose, camera: &PinholeCamera) -> Vec<Rgb> {
        self.radiance_view_with(world_from_eo, &CameraRays::new(camera))
    }

    /// [`Self::radiance_view`] with the camera's rays computed once by the caller.
    pub fn radiance_view_with(&self, world_from_eo: &Pose, rays: &CameraRays) -> Vec<Rgb> {
        let backend = BuiltinBackend::new(self.world.clone());
        eo::radiance(
            &backend,
            rays,
            &EffectSet::default(),
            std::slice::from_ref(world_from_eo),
        )
    }

    /// Number of primitives in the scene's acceleration structure.
    pub fn primitive_count(&self) -> usize {
        self.world.bvh.primitive_count()
    }
}
