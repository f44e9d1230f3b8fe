//! The simulator: a scene, a seed and the effects to simulate, turned into texel
//! frames. Frame `i` is a pure function of (scene, options, seed, i): it never
//! depends on which frames were rendered before or on the thread count.

use std::sync::Arc;

use texel::{EoFrame, FramePair, PinholeCamera, Pose, RangeFrame, Sensor, SensorModel};
use thiserror::Error;

use crate::effects::lens_distortion::effective_model;
use crate::effects::{Effect, EffectSet};
use crate::material::Rgb;
use crate::render::eo::Development;
use crate::render::lidar::{LidarRays, NoiseKey, echoes, render_range};
use crate::render::mitsuba::{MitsubaBackend, MitsubaRenderer};
use crate::render::{BackendKind, BuiltinBackend, CameraRays, RenderBackend, eo, world_ray};
use crate::scene::{MAX_EO_SIDE, MAX_LIDAR_SIDE, Scene};
use crate::world::{SurfaceSample, TruthHit};

/// Overrides of a scene's settings, for tests and tools (no file editing needed).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SimOptions {
    /// Seed of every random number (noise, dropouts); the trajectory's jitter has its
    /// own seed in the scene.
    pub seed: u64,
    /// Replaces the scene's effect list (`Some(vec![])` = no effects).
    pub effects: Option<Vec<Effect>>,
    /// Number of frames (fewer than the trajectory's, or more for orbits and walks).
    pub frames: Option<usize>,
    /// Lidar resolution `[width, height]`; intrinsics scale with it.
    pub lidar_size: Option<[u32; 2]>,
    /// EO resolution `[width, height]`; intrinsics scale with it.
    pub eo_size: Option<[u32; 2]>,
    pub backend: BackendKind,
}

#[derive(Debug, Error)]
pub enum SimError {
    #[error("the {backend} backend is not available: {reason}")]
    BackendUnavailable {
        backend: &'static str,
        reason: String,
    },
    /// The backend failed while rendering (the Mitsuba process died or refused).
    #[error("the {backend} backend failed: {reason}")]
    Backend {
        backend: &'static str,
        reason: String,
    },
    #[error("frame {index} does not exist: the simulation has {frames} frames")]
    FrameOutOfRange { index: usize, frames: usize },
    #[error("invalid option: {0}")]
    BadOption(String),
    #[error(transparent)]
    Capture(#[from] texel::capture::CaptureError),
}

/// One simulated texel frame with its ground truth.
#[derive(Debug, Clone)]
pub struct SimFrame {
    pub index: usize,
    /// Range and EO frames with equal timestamps.
    pub pair: FramePair,
    /// The true EO pose at the frame's timestamp.
    pub world_from_eo: Pose,
    pub timestamp_ns: u64,
}

/// The true surface point seen by each lidar pixel (no effects), row-major.
#[derive(Debug, Clone)]
pub struct LidarTruth {
    pub width: u32,
    pub height: u32,
    pub world_from_lidar: Pose,
    /// `None` where the pixel's ray meets nothing or the pixel has no ray.
    pub hits: Vec<Option<TruthHit>>,
}

/// Renders a scene's texel frames.
pub struct Simulator {
    scene: Scene,
    seed: u64,
    effects: EffectSet,
    sensor: Sensor,
    lidar_rays: LidarRays,
    eo_rays: CameraRays,
    /// How the EO images are developed with the simulation's effects.
    eo_development: Development,
    /// Renders with the simulation's effects (global illumination included).
    backend: Arc<dyn RenderBackend>,
    /// Renders the clean signal (`clean_*_at`): the same renderer without effects.
    clean_backend: Arc<dyn RenderBackend>,
    /// The Mitsuba process, when the Mitsuba backend renders.
    mitsuba: Option<Arc<MitsubaRenderer>>,
    frames: usize,
}

/// `camera` at another resolution: the same field of view, intrinsics scaled with the
/// pixel-centre convention (`c' = (c + 0.5)·s - 0.5`).
pub fn rescale_camera(camera: &PinholeCamera, width: u32, height: u32) -> PinholeCamera {
    let sx = f64::from(width) / f64::from(camera.width);
    let sy = f64::from(height) / f64::from(camera.height);
    PinholeCamera {
        width,
        height,
        fx: camera.fx * sx,
        fy: camera.fy * sy,
        cx: (camera.cx + 0.5) * sx - 0.5,
        cy: (camera.cy + 0.5) * sy - 0.5,
        skew: camera.skew * sx,
        distortion: camera.distortion,
    }
}

fn check_size(what: &str, size: [u32; 2], max: u32) -> Result<(), SimError> {
    if size[0] == 0 || size[1] == 0 || size[0] > max || size[1] > max {
        return Err(SimError::BadOption(format!(
            "{what} size {}x{} is outside 1..={max} per side",
            size[0], size[1]
        )));
    }
    Ok(())
}

impl Simulator {
    /// A simulator of the scene as its file describes it.
    pub fn new(scene: Scene, seed: u64) -> Result<Self, SimError> {
        Self::with_options(
            scene,
            &SimOptions {
                seed,
                ..SimOptions::default()
            },
        )
    }

    pub fn with_options(scene: Scene, options: &SimOptions) -> Result<Self, SimError> {
        let effects = match &options.effects {
            Some(list) => EffectSet::from_list(list).map_err(SimError::BadOption)?,
            None => scene.effect_set(),
        };
        let use_mitsuba = match (options.backend, &effects.global_illumination) {
            (BackendKind::Builtin, Some(_)) => {
                return Err(SimError::BadOption(
                    "global_illumination is simulated by the Mitsuba backend only \
                     (use --backend mitsuba, or leave the backend to be chosen)"
                        .into(),
                ));
            }
            (BackendKind::Builtin, None) => false,
            (BackendKind::Mitsuba, _) | (BackendKind::Auto, Some(_)) => true,
            (BackendKind::Auto, None) => false,
        };
        if use_mitsuba && effects.moving_lights.is_some() {
            return Err(SimError::BadOption(
                "moving_lights is simulated by the built-in backend only (the Mitsuba \
                 backend exports the scene's lights once)"
                    .into(),
            ));
        }
        let mut model = effective_model(scene.sensor(), effects.lens_distortion.as_ref());
        if let Some(size) = options.lidar_size {
            check_size("lidar", size, MAX_LIDAR_SIDE)?;
            model.lidar = rescale_camera(&model.lidar, size[0], size[1]);
        }
        if let Some(size) = options.eo_size {
            check_size("EO", size, MAX_EO_SIDE)?;
            model.eo = rescale_camera(&model.eo, size[0], size[1]);
        }
        let frames = options.frames.unwrap_or(scene.trajectory.frames);
        if frames == 0 {
            return Err(SimError::BadOption("frames must be at least 1".into()));
        }
        if let crate::trajectory::Path::Poses(p) = &scene.trajectory.path
            && frames > p.len()
        {
            return Err(SimError::BadOption(format!(
                "{frames} frames asked for, but the trajectory has {} poses",
                p.len()
            )));
        }
        let sensor = Sensor::new(model);
        let lidar_rays = LidarRays::new(&sensor.model.lidar, effects.mixed_pixels.as_ref());
        let eo_rays = CameraRays::new(&sensor.model.eo);
        let (backend, clean_backend, mitsuba): (Arc<dyn RenderBackend>, Arc<dyn RenderBackend>, _) =
            if use_mitsuba {
                let renderer =
                    Arc::new(MitsubaRenderer::start(&scene.world).map_err(|reason| {
                        SimError::BackendUnavailable {
                            backend: "mitsuba",
                            reason,
                        }
                    })?);
                (
                    Arc::new(MitsubaBackend::new(
                        renderer.clone(),
                        effects.global_illumination.clone(),
                    )),
                    Arc::new(MitsubaBackend::new(renderer.clone(), None)),
                    Some(renderer),
                )
            } else {
                let builtin: Arc<dyn RenderBackend> =
                    Arc::new(BuiltinBackend::new(scene.world.clone()));
                (builtin.clone(), builtin, None)
            };
        let eo_development = Development::new(&eo_rays, &effects);
        Ok(Self {
            seed: options.seed,
            effects,
            sensor,
            lidar_rays,
            eo_development,
            eo_rays,
            backend,
            clean_backend,
            mitsuba,
            frames,
            scene,
        })
    }

    /// The renderer in use: `"builtin"` or `"mitsuba"`.
    pub fn backend_name(&self) -> &'static str {
        self.backend.name()
    }

    /// The Mitsuba process, when the Mitsuba backend renders (start-up time, version).
    pub fn mitsuba(&self) -> Option<&Arc<MitsubaRenderer>> {
        self.mitsuba.as_ref()
    }

    /// Why the backend failed, if it did. Frames rendered after a failure are empty
    /// (no returns, black); [`Self::frame`] reports the failure instead.
    pub fn backend_failure(&self) -> Option<String> {
        self.backend.failure()
    }

    fn check_backend(&self) -> Result<(), SimError> {
        match self.backend.failure() {
            Some(reason) => Err(SimError::Backend {
                backend: self.backend.name(),
                reason,
            }),
            None => Ok(()),
        }
    }

    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// The effects that run.
    pub fn effects(&self) -> &EffectSet {
        &self.effects
    }

    /// The sensor model frames are rendered with, and that a capture carries (the
    /// scene's sensor file, with distortion only under the `lens_distortion` effect,
    /// at the resolution asked for).
    pub fn sensor_model(&self) -> &SensorModel {
        &self.sensor.model
    }

    /// [`Self::sensor_model`] with its ray table, as fusion takes it.
    pub fn sensor(&self) -> &Sensor {
        &self.sensor
    }

    pub fn frame_count(&self) -> usize {
        self.frames
    }

    pub fn frame_rate_hz(&self) -> f64 {
        self.scene.trajectory.rate_hz
    }

    pub fn timestamp_ns(&self, index: usize) -> u64 {
        self.scene.trajectory.timestamp_ns(index)
    }

    /// The true `world_from_eo` of frame `index` (defined past the last frame too).
    pub fn true_pose(&self, index: usize) -> Pose {
        self.scene.trajectory.frame_pose(index)
    }

    /// The lidar's pose for an EO pose.
    pub fn world_from_lidar(&self, world_from_eo: &Pose) -> Pose {
        world_from_eo * self.sensor.model.eo_from_lidar
    }

    /// Renders frame `index` with every effect of the simulation.
    pub fn frame(&self, index: usize) -> Result<SimFrame, SimError> {
        if index >= self.frames {
            return Err(SimError::FrameOutOfRange {
                index,
                frames: self.frames,
            });
        }
        let world_from_eo = self.true_pose(index);
        let timestamp_ns = self.timestamp_ns(index);
        let key = NoiseKey {
            seed: self.seed,
            frame: index as u64,
        };
        let eo_poses: Vec<Pose> = match &self.effects.motion_blur {
            Some(blur) => {
                let t = self.scene.trajectory.frame_time_s(index);
                blur.offsets_s()
                    .into_iter()
                    .map(|dt| self.scene.trajectory.pose_at(t + dt))
                    .collect()
            }
            None => vec![world_from_eo],
        };
        let (range, eo) = rayon::join(
            || self.range_frame(&world_from_eo, key, timestamp_ns, index as u32),
            || self.eo_frame(&eo_poses, key, timestamp_ns),
        );
        self.check_backend()?;
        Ok(SimFrame {
            index,
            pair: FramePair { range, eo },
            world_from_eo,
            timestamp_ns,
        })
    }

    fn range_frame(
        &self,
        world_from_eo: &Pose,
        key: NoiseKey,
        timestamp_ns: u64,
        seq: u32,
    ) -> RangeFrame {
        render_range(
            self.backend.as_ref(),
            &self.sensor.model,
            &self.lidar_rays,
            &self.effects,
            &self.world_from_lidar(world_from_eo),
            key,
            timestamp_ns,
            seq,
        )
    }

    fn eo_frame(&self, poses: &[Pose], key: NoiseKey, timestamp_ns: u64) -> EoFrame {
        let linear = match &self.effects.moving_lights {
            // The lights of this instant over the scene's geometry (shared, not copied).
            Some(moving) => {
                let world = &self.scene.world;
                let t_s = timestamp_ns as f64 * 1.0e-9;
                let lit = world.with_lighting(moving.lighting_at(&world.lighting, t_s));
                let backend = BuiltinBackend::new(Arc::new(lit));
                eo::radiance(&backend, &self.eo_rays, &self.effects, poses)
            }
            None => eo::radiance(self.backend.as_ref(), &self.eo_rays, &self.effects, poses),
        };
        self.eo_development.develop(&linear, key, timestamp_ns)
    }

    /// A texel frame at any pose, with the simulation's effects except motion blur
    /// (a single pose has no motion); `noise_frame` keys the random numbers.
    pub fn render_at(
        &self,
        world_from_eo: &Pose,
        noise_frame: u64,
        timestamp_ns: u64,
    ) -> FramePair {
        let key = NoiseKey {
            seed: self.seed,
            frame: noise_frame,
        };
        let seq = noise_frame as u32;
        let (range, eo) = rayon::join(
            || self.range_frame(world_from_eo, key, timestamp_ns, seq),
            || self.eo_frame(std::slice::from_ref(world_from_eo), key, timestamp_ns),
        );
        FramePair { range, eo }
    }

    /// The range frame at any pose with the simulation's lidar effects.
    pub fn range_at(
        &self,
        world_from_eo: &Pose,
        noise_frame: u64,
        timestamp_ns: u64,
    ) -> RangeFrame {
        let key = NoiseKey {
            seed: self.seed,
            frame: noise_frame,
        };
        self.range_frame(world_from_eo, key, timestamp_ns, noise_frame as u32)
    }

    /// The clean range frame at any pose: exact radial distances, no effects.
    pub fn clean_range_at(&self, world_from_eo: &Pose, timestamp_ns: u64) -> RangeFrame {
        render_range(
            self.clean_backend.as_ref(),
            &self.sensor.model,
            &self.lidar_rays,
            &EffectSet::default(),
            &self.world_from_lidar(world_from_eo),
            NoiseKey { seed: 0, frame: 0 },
            timestamp_ns,
            0,
        )
    }

    /// The clean EO image at any pose through the simulation's EO camera model.
    pub fn clean_eo_at(&self, world_from_eo: &Pose, timestamp_ns: u64) -> EoFrame {
        let clean = EffectSet::default();
        let linear = eo::radiance(
            self.clean_backend.as_ref(),
            &self.eo_rays,
            &clean,
            std::slice::from_ref(world_from_eo),
        );
        eo::develop(
            &linear,
            &self.eo_rays,
            &clean,
            NoiseKey { seed: 0, frame: 0 },
            timestamp_ns,
        )
    }

    /// The linear radiance every pixel of the simulation's EO camera receives at any
    /// pose, before vignetting, exposure, noise and the response curve (1.0 is white
    /// at 0 EV): the truth a high-dynamic-range result is scored against. A frame
    /// developed with the `exposure` effect's linear response holds
    /// `min(1, radiance × exposure_time / exposure_time_s)` per channel, in 8 bits.
    pub fn clean_radiance_at(&self, world_from_eo: &Pose) -> Vec<Rgb> {
        eo::radiance(
            self.clean_backend.as_ref(),
            &self.eo_rays,
            &EffectSet::default(),
            std::slice::from_ref(world_from_eo),
        )
    }

    /// The lidar echoes (range, incidence, reflectivity, object) of every pixel at a
    /// pose, after the beam geometry (`mixed_pixels`) but before dropouts and noise.
    pub fn echoes_at(&self, world_from_eo: &Pose) -> Vec<Option<SurfaceSample>> {
        echoes(
            self.backend.as_ref(),
            &self.lidar_rays,
            &self.effects,
            &self.world_from_lidar(world_from_eo),
        )
    }

    /// The true surface point of every lidar pixel at a pose (f64, no effects).
    pub fn lidar_truth_at(&self, world_from_eo: &Pose) -> LidarTruth {
        use rayon::prelude::*;
        let world_from_lidar = self.world_from_lidar(world_from_eo);
        let hits = self
            .lidar_rays
            .centre
            .rays
            .par_iter()
            .map(|r| world_ray(&world_from_lidar, r).and_then(|ray| self.scene.world.truth(&ray)))
            .collect();
        LidarTruth {
            width: self.sensor.model.lidar.width,
            height: self.sensor.model.lidar.height,
            world_from_lidar,
            hits,
        }
    }

    /// [`Self::lidar_truth_at`] at frame `index`'s true pose.
    pub fn lidar_truth(&self, index: usize) -> LidarTruth {
        self.lidar_truth_at(&self.true_pose(index))
    }
}
