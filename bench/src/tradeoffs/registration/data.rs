//! The data the registration trade-offs are measured on: simulator captures of the
//! scenes (rendered once into a cache directory, then read back and fused like any
//! capture), and pairs of scans a known pose apart for the pairwise comparison.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result, bail};
use nalgebra::{Translation3, UnitQuaternion, Vector3};
use texel::capture::{PoseTopic, SensorCache, TexelItem, open_texel_frames};
use texel::{FuseConfig, PinholeCamera, Pose, SensorModel, TexelScan};

/// A fused capture with its true poses.
pub struct Sequence {
    pub scene: String,
    pub scans: Vec<Arc<TexelScan>>,
    /// `world_from_scan` of each scan, from `/truth/pose`.
    pub truth: Vec<Pose>,
    pub lidar: PinholeCamera,
    /// The sensor of the first frame (both camera models).
    pub sensor: SensorModel,
    pub path_length_m: f64,
}

/// Which capture to make of a scene.
#[derive(Debug, Clone, Copy)]
pub struct SequenceSpec<'a> {
    pub scene: &'a str,
    pub frames: usize,
    pub seed: u64,
    /// For an orbit: the frames of one full turn, replacing the scene's (a slower
    /// walk round the same circle).
    pub orbit_period_frames: Option<usize>,
}

/// A scene of `configs/scenes/` rendered (or found in the cache) and fused.
pub fn sequence(scenes_dir: &Path, cache_dir: &Path, spec: &SequenceSpec<'_>) -> Result<Sequence> {
    let capture = cached_capture(scenes_dir, cache_dir, spec)?;
    read_sequence(&capture, spec.scene)
}

/// The capture of a spec, rendered into `cache_dir` unless a previous run left it
/// there (the name holds scene, frames, period and seed; delete the directory after
/// editing a scene file).
pub fn cached_capture(
    scenes_dir: &Path,
    cache_dir: &Path,
    spec: &SequenceSpec<'_>,
) -> Result<PathBuf> {
    let SequenceSpec {
        scene,
        frames,
        seed,
        orbit_period_frames,
    } = *spec;
    std::fs::create_dir_all(cache_dir)
        .with_context(|| format!("cannot create the cache directory {}", cache_dir.display()))?;
    let period = orbit_period_frames.map_or(String::new(), |p| format!("-period{p}"));
    let out = cache_dir.join(format!("{scene}-{frames}f{period}-seed{seed}.mcap"));
    if out.exists() {
        return Ok(out);
    }
    let sim = simulator(scenes_dir, scene, frames, seed, orbit_period_frames)?;
    let partial = out.with_extension("partial.mcap");
    eprintln!("rendering {scene} ({frames} frames) into {}", out.display());
    sims::render_capture(&sim, &partial, &Default::default(), &mut |_, _| {})
        .with_context(|| format!("rendering {scene}"))?;
    std::fs::rename(&partial, &out)
        .with_context(|| format!("cannot move {} into place", partial.display()))?;
    Ok(out)
}

/// A simulator of a scene file with the scene's effects, `frames` frames and, for an
/// orbit, `orbit_period_frames` a turn.
pub fn simulator(
    scenes_dir: &Path,
    scene: &str,
    frames: usize,
    seed: u64,
    orbit_period_frames: Option<usize>,
) -> Result<sims::Simulator> {
    let path = scenes_dir.join(format!("{scene}.toml"));
    let mut loaded =
        sims::Scene::load(&path).with_context(|| format!("loading {}", path.display()))?;
    if let (Some(p), sims::trajectory::Path::Orbit { period_frames, .. }) =
        (orbit_period_frames, &mut loaded.trajectory.path)
    {
        *period_frames = p.max(1);
    }
    let options = sims::SimOptions {
        seed,
        frames: Some(frames),
        ..Default::default()
    };
    sims::Simulator::with_options(loaded, &options).with_context(|| format!("simulating {scene}"))
}

/// Reads and fuses every texel frame of a capture that has `/truth/pose`.
pub fn read_sequence(capture: &Path, scene: &str) -> Result<Sequence> {
    let mut truth_by_time: BTreeMap<u64, Pose> = BTreeMap::new();
    let mut pairs = Vec::new();
    for item in open_texel_frames(capture)? {
        match item {
            Err(e) if e.is_fatal() => return Err(e.into()),
            Err(_) => {}
            Ok(TexelItem::Pair { pair, sensor }) => pairs.push((pair, sensor)),
            Ok(TexelItem::Pose {
                topic: PoseTopic::Truth,
                timestamp_ns,
                world_from_eo,
            }) => {
                truth_by_time.insert(timestamp_ns, world_from_eo);
            }
            Ok(TexelItem::Pose { .. } | TexelItem::Anchor(_)) => {}
        }
    }
    let Some((_, first_model)) = pairs.first() else {
        bail!("{}: no texel frames", capture.display());
    };
    let lidar = first_model.lidar.clone();
    let sensor = (**first_model).clone();
    // Each frame is fused with its own sensor model (a capture may change it midway);
    // the cache rebuilds the ray tables only when the model changes.
    let mut sensors = SensorCache::new();
    let mut scans = Vec::with_capacity(pairs.len());
    let mut truth = Vec::with_capacity(pairs.len());
    for (pair, model) in pairs {
        let t = pair.timestamp_ns();
        let Some(pose) = truth_by_time.get(&t) else {
            bail!("{}: frame at {t} ns has no /truth/pose", capture.display());
        };
        let scan = sensors
            .fuse(pair, &model, &FuseConfig::default())
            .with_context(|| format!("fusing the frame at {t} ns"))?;
        scans.push(Arc::new(scan));
        truth.push(*pose);
    }
    let path_length_m = truth
        .windows(2)
        .map(|w| (w[1].translation.vector - w[0].translation.vector).norm())
        .sum();
    Ok(Sequence {
        scene: scene.to_string(),
        scans,
        truth,
        lidar,
        sensor,
        path_length_m,
    })
}

/// Two scans of one scene a known pose apart.
pub struct ScanPair {
    pub scene: String,
    pub target: Arc<TexelScan>,
    pub source: Arc<TexelScan>,
    pub lidar: PinholeCamera,
    pub eo: Arc<PinholeCamera>,
    /// True `target_from_source`.
    pub truth: Pose,
    /// The initial guess both methods start from.
    pub initial: Pose,
}

/// A rotation of `angle_deg` about `axis` followed by a translation of `dist_m` along
/// `dir` (both normalised; zero vectors give no motion).
pub fn perturbation(angle_deg: f64, axis: [f64; 3], dist_m: f64, dir: [f64; 3]) -> Pose {
    let axis = Vector3::from(axis);
    let dir = Vector3::from(dir);
    let rotation = match nalgebra::Unit::try_new(axis, 1.0e-12) {
        Some(a) => UnitQuaternion::from_axis_angle(&a, angle_deg.to_radians()),
        None => UnitQuaternion::identity(),
    };
    let t = if dir.norm() > 1.0e-12 {
        dir.normalize() * dist_m
    } else {
        Vector3::zeros()
    };
    Pose::from_parts(Translation3::from(t), rotation)
}

/// A deterministic direction generator (xorshift), so pair sets are reproducible.
struct Directions(u64);

impl Directions {
    fn unit(&mut self) -> [f64; 3] {
        loop {
            let mut c = [0.0; 3];
            for x in &mut c {
                self.0 ^= self.0 << 13;
                self.0 ^= self.0 >> 7;
                self.0 ^= self.0 << 17;
                *x = ((self.0 >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0;
            }
            let n = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
            if n > 0.1 && n <= 1.0 {
                return c.map(|x| x / n);
            }
        }
    }
}

/// `count` pairs of `scene`: the target at frames spread over its trajectory, the
/// source `angle_deg` and `dist_m` away from it about and along seeded random
/// directions, with range noise only (the sensor's sigma) and the source's truth as
/// `target_from_source`; the initial guess is the identity (the full perturbation to
/// recover).
pub fn perturbed_pairs(
    scenes_dir: &Path,
    scene: &str,
    count: usize,
    angle_deg: f64,
    dist_m: f64,
    seed: u64,
) -> Result<Vec<ScanPair>> {
    let path = scenes_dir.join(format!("{scene}.toml"));
    let loaded = sims::Scene::load(&path).with_context(|| format!("loading {}", path.display()))?;
    let trajectory_frames = loaded.frame_count().max(1);
    let options = sims::SimOptions {
        seed,
        effects: Some(vec![sims::Effect::RangeNoise(Default::default())]),
        // The pairwise comparison is geometric: a small EO image keeps rendering fast.
        eo_size: Some([160, 120]),
        ..Default::default()
    };
    let sim = sims::Simulator::with_options(loaded, &options)
        .with_context(|| format!("simulating {scene}"))?;
    let sensor = sim.sensor().clone();
    let mut directions = Directions(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    let mut out = Vec::with_capacity(count);
    for k in 0..count {
        let frame = (k * trajectory_frames) / count.max(1);
        let world_from_target = sim.true_pose(frame);
        let truth = perturbation(angle_deg, directions.unit(), dist_m, directions.unit());
        let world_from_source = world_from_target * truth;
        let render = |pose: &Pose, noise_frame: u64| -> Result<Arc<TexelScan>> {
            let pair = sim.render_at(pose, noise_frame, noise_frame * 100_000_000);
            Ok(Arc::new(
                texel::fuse(&pair.range, pair.eo, &sensor, &FuseConfig::default())
                    .with_context(|| format!("fusing a {scene} pair"))?,
            ))
        };
        out.push(ScanPair {
            scene: scene.to_string(),
            target: render(&world_from_target, 2 * k as u64)?,
            source: render(&world_from_source, 2 * k as u64 + 1)?,
            lidar: sensor.model.lidar.clone(),
            eo: Arc::new(sensor.model.eo.clone()),
            truth,
            initial: Pose::identity(),
        });
    }
    Ok(out)
}
