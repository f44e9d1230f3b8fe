//! Pairwise registration side by side with Open3D's point-to-plane ICP on the same
//! scan pairs and initial guesses: the pairs are written as `.npy` point arrays with
//! a JSON manifest, `scripts/python/open3d_icp.py` runs Open3D on them (one thread),
//! and Texel's `align_pair` runs on the same pairs here (one core). Both times
//! include the normals each needs: Open3D's normal estimation on the target, and
//! both range-image pyramids (points, normals, levels) on Texel's side.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

use anyhow::{Context, Result, bail};
use nalgebra::{Matrix4, Rotation3, Translation3, UnitQuaternion};
use serde::{Deserialize, Serialize};
use texel::Pose;
use texel::pose::pose_difference;

use super::data::ScanPair;
use texel_register::clock::{Stopwatch, quantile};
use texel_register::{AlignConfig, PyramidOptions, ScanPyramid, align_pair};

/// One pair's outcome for one method.
#[derive(Debug, Clone, Serialize)]
pub struct PairOutcome {
    pub name: String,
    pub scene: String,
    /// The method and its setting ("open3d", or Texel's setting name).
    pub method: String,
    pub rotation_error_deg: f64,
    pub translation_error_mm: f64,
    /// CPU time (one core), milliseconds: normals (pyramids) and the alignment.
    pub normals_ms: f64,
    pub align_ms: f64,
    pub ok: bool,
}

/// A pair's file name stem.
fn stem(k: usize, pair: &ScanPair) -> String {
    format!("{}-{k:02}", pair.scene)
}

/// Writes `points` (N x 3 float32, C order) as a NumPy `.npy` file (format 1.0).
pub fn write_npy(path: &Path, points: &[[f32; 3]]) -> Result<()> {
    let mut header = format!(
        "{{'descr': '<f4', 'fortran_order': False, 'shape': ({}, 3), }}",
        points.len()
    );
    // Magic (6) + version (2) + length (2) + header + '\n', padded to 64 bytes.
    let unpadded = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let length = u16::try_from(header.len()).context("npy header too long")?;
    let mut bytes = Vec::with_capacity(10 + header.len() + points.len() * 12);
    bytes.extend_from_slice(b"\x93NUMPY\x01\x00");
    bytes.extend_from_slice(&length.to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    for p in points {
        for c in p {
            bytes.extend_from_slice(&c.to_le_bytes());
        }
    }
    let mut file =
        std::fs::File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
    file.write_all(&bytes)
        .with_context(|| format!("cannot write {}", path.display()))
}

fn matrix(pose: &Pose) -> [[f64; 4]; 4] {
    let m = pose.to_homogeneous();
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

fn pose_from_rows(rows: &[[f64; 4]; 4]) -> Result<Pose> {
    let m = Matrix4::from_fn(|r, c| rows[r][c]);
    if !m.iter().all(|x| x.is_finite()) {
        bail!("a non-finite transformation");
    }
    let rotation = Rotation3::from_matrix(&m.fixed_view::<3, 3>(0, 0).into_owned());
    Ok(Pose::from_parts(
        Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]),
        UnitQuaternion::from_rotation_matrix(&rotation),
    ))
}

#[derive(Serialize)]
struct ManifestPair {
    name: String,
    source: String,
    target: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    source_colors: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    target_colors: Option<String>,
    initial: [[f64; 4]; 4],
}

#[derive(Serialize)]
struct Manifest {
    max_correspondence_distance_m: f64,
    max_iterations: u32,
    normal_radius_m: f64,
    normal_max_nn: u32,
    repeats: u32,
    method: &'static str,
    pairs: Vec<ManifestPair>,
}

#[derive(Deserialize)]
struct ResultPair {
    name: String,
    transformation: [[f64; 4]; 4],
    normals_ms: f64,
    icp_ms: f64,
}

#[derive(Deserialize)]
struct Results {
    open3d_version: String,
    pairs: Vec<ResultPair>,
}

/// Open3D's settings for the comparison: the same correspondence gate as Texel's
/// finest level, its usual iteration cap, normals from up to 30 neighbours within
/// 10 cm.
pub struct Open3dSettings {
    pub max_correspondence_distance_m: f64,
    pub max_iterations: u32,
    pub repeats: u32,
    /// Park, Zhou & Koltun's colored ICP (each point with its texel colour) instead
    /// of point-to-plane.
    pub colored: bool,
}

/// Each vertex's texel colour in [0, 1] (mid grey where the EO camera did not see
/// it).
fn vertex_colours(scan: &texel::TexelScan) -> Vec<[f32; 3]> {
    (0..scan.vertex_count())
        .map(|v| {
            scan.vertex_colour(v)
                .map_or([0.5; 3], |c| c.map(|x| f32::from(x) / 255.0))
        })
        .collect()
}

/// Runs Open3D on `pairs` with `python`; returns its version and outcomes.
pub fn run_open3d(
    python: &Path,
    script: &Path,
    dir: &Path,
    pairs: &[ScanPair],
    settings: &Open3dSettings,
) -> Result<(String, Vec<PairOutcome>)> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let mut manifest = Manifest {
        max_correspondence_distance_m: settings.max_correspondence_distance_m,
        max_iterations: settings.max_iterations,
        normal_radius_m: 0.1,
        normal_max_nn: 30,
        repeats: settings.repeats,
        method: if settings.colored {
            "colored"
        } else {
            "point_to_plane"
        },
        pairs: Vec::new(),
    };
    for (k, pair) in pairs.iter().enumerate() {
        let name = stem(k, pair);
        let (source, target) = (format!("{name}-source.npy"), format!("{name}-target.npy"));
        write_npy(&dir.join(&source), &pair.source.vertices)?;
        write_npy(&dir.join(&target), &pair.target.vertices)?;
        let (mut source_colors, mut target_colors) = (None, None);
        if settings.colored {
            let (s, t) = (
                format!("{name}-source-rgb.npy"),
                format!("{name}-target-rgb.npy"),
            );
            write_npy(&dir.join(&s), &vertex_colours(&pair.source))?;
            write_npy(&dir.join(&t), &vertex_colours(&pair.target))?;
            (source_colors, target_colors) = (Some(s), Some(t));
        }
        manifest.pairs.push(ManifestPair {
            name,
            source,
            target,
            source_colors,
            target_colors,
            initial: matrix(&pair.initial),
        });
    }
    let manifest_path = dir.join("manifest.json");
    let result_path = dir.join("open3d-result.json");
    std::fs::write(&manifest_path, serde_json::to_string_pretty(&manifest)?)
        .with_context(|| format!("cannot write {}", manifest_path.display()))?;
    let output = Command::new(python)
        .arg(script)
        .arg(&manifest_path)
        .arg(&result_path)
        .env("OMP_NUM_THREADS", "1")
        .output()
        .with_context(|| {
            format!(
                "cannot run {} (the venv of scripts/setup.sh, or --python)",
                python.display()
            )
        })?;
    if !output.status.success() {
        bail!(
            "{} failed: {}",
            script.display(),
            String::from_utf8_lossy(&output.stderr)
        );
    }
    let text = std::fs::read_to_string(&result_path)
        .with_context(|| format!("cannot read {}", result_path.display()))?;
    let results: Results = serde_json::from_str(&text)
        .with_context(|| format!("{} is not the expected JSON", result_path.display()))?;
    let mut outcomes = Vec::with_capacity(pairs.len());
    for (k, pair) in pairs.iter().enumerate() {
        let name = stem(k, pair);
        let Some(r) = results.pairs.iter().find(|r| r.name == name) else {
            bail!("Open3D's result has no pair {name}");
        };
        let estimate = pose_from_rows(&r.transformation).with_context(|| name.clone())?;
        let (angle, dist) = pose_difference(&estimate, &pair.truth);
        outcomes.push(PairOutcome {
            name,
            scene: pair.scene.clone(),
            method: if settings.colored {
                "open3d colored".to_string()
            } else {
                "open3d".to_string()
            },
            rotation_error_deg: angle.to_degrees(),
            translation_error_mm: dist * 1000.0,
            normals_ms: r.normals_ms,
            align_ms: r.icp_ms,
            ok: true,
        });
    }
    Ok((results.open3d_version, outcomes))
}

/// Texel's pairwise registration on the same pairs, on this thread, `repeats` times
/// each (median CPU times); `setting` names `config` in the outcomes.
pub fn run_texel(
    pairs: &[ScanPair],
    setting: &str,
    config: &AlignConfig,
    repeats: u32,
) -> Vec<PairOutcome> {
    let config = AlignConfig {
        parallel: false,
        ..config.clone()
    };
    let options = PyramidOptions {
        levels: config.pyramid_levels,
        eo_levels: if config.photometric.enabled() {
            config.photometric.eo_levels
        } else {
            0
        },
        first_eo_level: config.photometric.finest_eo_level,
    };
    pairs
        .iter()
        .enumerate()
        .map(|(k, pair)| {
            let (mut normals, mut aligns) = (Vec::new(), Vec::new());
            let mut last = None;
            for _ in 0..repeats.max(1) {
                let watch = Stopwatch::start();
                let target = ScanPyramid::build_with(
                    Arc::clone(&pair.target),
                    &pair.lidar,
                    Some(&pair.eo),
                    options,
                );
                let source = ScanPyramid::build_with(
                    Arc::clone(&pair.source),
                    &pair.lidar,
                    Some(&pair.eo),
                    options,
                );
                normals.push(watch.elapsed().cpu_ms);
                let watch = Stopwatch::start();
                let alignment = align_pair(&source, &target, &pair.initial, &config);
                aligns.push(watch.elapsed().cpu_ms);
                last = Some(alignment);
            }
            let (estimate, ok) = last
                .map(|a| (a.world_from_source, a.is_ok()))
                .unwrap_or((pair.initial, false));
            let (angle, dist) = pose_difference(&estimate, &pair.truth);
            PairOutcome {
                name: stem(k, pair),
                scene: pair.scene.clone(),
                method: setting.to_string(),
                rotation_error_deg: angle.to_degrees(),
                translation_error_mm: dist * 1000.0,
                normals_ms: quantile(&normals, 0.5),
                align_ms: quantile(&aligns, 0.5),
                ok,
            }
        })
        .collect()
}

/// The script's path in the repository.
pub fn script(repo: &Path) -> PathBuf {
    repo.join("scripts").join("python").join("open3d_icp.py")
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn npy_headers_are_padded_to_64_bytes() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.npy");
        write_npy(&path, &[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00");
        let len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!((10 + len) % 64, 0);
        assert_eq!(bytes[10 + len - 1], b'\n');
        assert_eq!(bytes.len(), 10 + len + 24);
        assert_eq!(
            f32::from_le_bytes(bytes[10 + len..14 + len].try_into().unwrap()),
            1.0
        );
        let pose = Pose::from_parts(
            Translation3::new(0.1, -0.2, 0.3),
            UnitQuaternion::from_euler_angles(0.1, 0.2, -0.3),
        );
        let back = pose_from_rows(&matrix(&pose)).unwrap();
        let (a, d) = pose_difference(&pose, &back);
        assert!(a < 1e-12 && d < 1e-12);
    }
}
