//! The Mitsuba 3 backend: the scene exported once ([`super::mitsuba_scene`]), one
//! long-lived Python process (`sims/python/mitsuba_render.py`, in the venv that
//! `scripts/setup.sh` makes) that loads it, and a request per render: the exact
//! per-pixel rays go out (the lidar's ray table, the EO camera's unprojected pixel
//! centres, distortion and principal point included), distances or radiance come back,
//! and become the same clean echoes and radiance the built-in backend produces, so
//! every effect applies identically afterwards.
//!
//! Mitsuba runs as `llvm_ad_rgb` (vectorised over all rays), which needs libLLVM 19
//! (Debian's `libllvm19`; the older LLVM 15 crashes it): `DRJIT_LIBLLVM_PATH` if set,
//! else found in the standard library directories.

use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde_json::json;
use texel::Pose;

use super::mitsuba_scene::{ExportedScene, export};
use super::{CameraRays, RenderBackend, world_ray};
use crate::effects::GlobalIllumination;
use crate::material::{Rgb, luminance};
use crate::rng::mix64;
use crate::world::{SurfaceSample, World};

/// The Python side, written next to the exported scene.
const SCRIPT: &str = include_str!("../../python/mitsuba_render.py");
/// Longest JSON line accepted from the Python side.
const MAX_LINE: u64 = 1 << 16;
/// Most rays in one request (the Python side's limit too).
const MAX_RAYS: usize = 1 << 26;
/// How long a closing Python process may take before it is killed.
const EXIT_GRACE: Duration = Duration::from_secs(5);

/// The venv that `scripts/setup.sh` creates: `$TEXEL_VENV`, else
/// `$XDG_CACHE_HOME/texel/venv`, else `~/.cache/texel/venv`.
pub fn venv_dir() -> PathBuf {
    if let Some(v) = std::env::var_os("TEXEL_VENV") {
        return PathBuf::from(v);
    }
    let cache = std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))
        .unwrap_or_else(|| PathBuf::from(".cache"));
    cache.join("texel").join("venv")
}

/// libLLVM for Dr.Jit: `$DRJIT_LIBLLVM_PATH`, else LLVM 19 (the version Mitsuba 3.9
/// runs with) in the standard library directories.
pub fn find_libllvm() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("DRJIT_LIBLLVM_PATH") {
        return Some(PathBuf::from(p));
    }
    let mut dirs = vec![
        PathBuf::from("/usr/lib/llvm-19/lib"),
        PathBuf::from("/usr/lib"),
        PathBuf::from("/usr/lib64"),
    ];
    if let Ok(entries) = std::fs::read_dir("/usr/lib") {
        // Multiarch directories (x86_64-linux-gnu, aarch64-linux-gnu, ...).
        let mut multiarch: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.to_string_lossy().ends_with("-linux-gnu"))
            .collect();
        multiarch.sort();
        dirs.splice(1..1, multiarch);
    }
    let names = [
        "libLLVM-19.so",
        "libLLVM.so.19.1",
        "libLLVM-19.so.1",
        "libLLVM.so.1",
    ];
    dirs.iter()
        .flat_map(|d| names.iter().map(move |n| d.join(n)))
        .find(|p| p.exists())
}

/// What the Mitsuba backend needs from this machine.
#[derive(Debug, Clone)]
pub struct MitsubaSetup {
    pub python: PathBuf,
    pub libllvm: PathBuf,
}

impl MitsubaSetup {
    /// The venv's Python and libLLVM 19, or what is missing and how to get it.
    pub fn discover() -> Result<Self, String> {
        let python = venv_dir().join("bin").join("python");
        if !python.exists() {
            return Err(format!(
                "the Python venv with Mitsuba is missing at {} (run scripts/setup.sh, or \
                 set TEXEL_VENV)",
                python.display()
            ));
        }
        let libllvm = find_libllvm().ok_or(
            "libLLVM 19 was not found (Debian package libllvm19, installed by \
             scripts/setup.sh; or set DRJIT_LIBLLVM_PATH)",
        )?;
        Ok(Self { python, libllvm })
    }
}

struct Worker {
    child: Child,
    stdin: ChildStdin,
    stdout: BufReader<ChildStdout>,
}

#[derive(Default)]
struct Session {
    worker: Option<Worker>,
    /// The first failure; every later request fails with it.
    failure: Option<String>,
}

/// What Mitsuba reports for a ray's nearest hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MitsubaHit {
    /// Distance along the unit ray, metres (computed in f32).
    pub distance_m: f64,
    /// |cos| of the angle between the ray and the geometric normal.
    pub cos_incidence: f64,
    pub object: u32,
    pub material: u32,
    /// Diffuse reflectance at the hit, point-sampled (no footprint filtering).
    pub albedo: Rgb,
}

/// One Mitsuba process with one exported scene, shared by backend views.
pub struct MitsubaRenderer {
    dir: tempfile::TempDir,
    session: Mutex<Session>,
    scene: ExportedScene,
    /// Per material: the lidar reflectivity, when the material fixes it.
    reflectivity: Vec<Option<f32>>,
    /// Wall-clock time from export to the process being ready.
    pub startup: Duration,
    /// Mitsuba's version, as the process reported it.
    pub version: String,
}

impl std::fmt::Debug for MitsubaRenderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MitsubaRenderer")
            .field("dir", &self.dir.path())
            .field("shapes", &self.scene.shape_count)
            .field("version", &self.version)
            .finish_non_exhaustive()
    }
}

fn read_line(stdout: &mut BufReader<ChildStdout>) -> Result<serde_json::Value, String> {
    let mut line = String::new();
    stdout
        .by_ref()
        .take(MAX_LINE)
        .read_line(&mut line)
        .map_err(|e| format!("reading from the Mitsuba process: {e}"))?;
    if line.is_empty() {
        return Err("the Mitsuba process exited".into());
    }
    serde_json::from_str(&line).map_err(|e| {
        format!(
            "the Mitsuba process sent an unreadable line ({e}): {:?}",
            line.chars().take(200).collect::<String>()
        )
    })
}

fn error_text(v: &serde_json::Value) -> String {
    v.get("error")
        .and_then(|e| e.as_str())
        .unwrap_or("(no message)")
        .to_string()
}

impl MitsubaRenderer {
    /// Exports `world`, starts the Python process and waits until it has loaded the
    /// scene.
    pub fn start(world: &World) -> Result<Self, String> {
        let setup = MitsubaSetup::discover()?;
        let start = Instant::now();
        let dir = tempfile::Builder::new()
            .prefix("texel-mitsuba-")
            .tempdir()
            .map_err(|e| format!("cannot make a temporary directory: {e}"))?;
        let scene = export(world, dir.path())?;
        let script = dir.path().join("mitsuba_render.py");
        std::fs::write(&script, SCRIPT)
            .map_err(|e| format!("cannot write {}: {e}", script.display()))?;
        let log_path = dir.path().join("mitsuba.log");
        let log = std::fs::File::create(&log_path)
            .map_err(|e| format!("cannot write {}: {e}", log_path.display()))?;
        let mut child = Command::new(&setup.python)
            .arg(&script)
            .arg(dir.path())
            .env("DRJIT_LIBLLVM_PATH", &setup.libllvm)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::from(log))
            .spawn()
            .map_err(|e| format!("cannot run {}: {e}", setup.python.display()))?;
        let (Some(stdin), Some(stdout)) = (child.stdin.take(), child.stdout.take()) else {
            let _ = child.kill();
            return Err("the Mitsuba process has no pipes".into());
        };
        let mut worker = Worker {
            child,
            stdin,
            stdout: BufReader::new(stdout),
        };
        let ready = read_line(&mut worker.stdout);
        let ready = match ready {
            Ok(v) if v.get("ready").and_then(|r| r.as_bool()) == Some(true) => v,
            other => {
                let why = match other {
                    Ok(v) => error_text(&v),
                    Err(e) => e,
                };
                close(worker, false);
                return Err(format!(
                    "Mitsuba did not start: {why}{}",
                    log_tail(&log_path)
                ));
            }
        };
        let version = ready
            .get("mitsuba")
            .and_then(|v| v.as_str())
            .unwrap_or("?")
            .to_string();
        Ok(Self {
            dir,
            session: Mutex::new(Session {
                worker: Some(worker),
                failure: None,
            }),
            scene,
            reflectivity: world
                .materials
                .iter()
                .map(|m| m.lidar_reflectivity)
                .collect(),
            startup: start.elapsed(),
            version,
        })
    }

    /// The first failure of the process, if any (every later request fails too).
    pub fn failure(&self) -> Option<String> {
        self.session.lock().ok().and_then(|s| s.failure.clone())
    }

    /// Number of Mitsuba shapes the scene became.
    pub fn shape_count(&self) -> usize {
        self.scene.shape_count
    }

    /// One request: `header` plus `rays` (6 floats each), `per_ray` floats back each.
    fn request(
        &self,
        mut header: serde_json::Value,
        rays: &[f32],
        per_ray: usize,
    ) -> Result<Vec<f32>, String> {
        let n = rays.len() / 6;
        if n > MAX_RAYS {
            return Err(format!("{n} rays in one request (at most {MAX_RAYS})"));
        }
        header["n"] = json!(n);
        let mut session = self
            .session
            .lock()
            .map_err(|_| "the Mitsuba session lock is poisoned".to_string())?;
        if let Some(f) = &session.failure {
            return Err(f.clone());
        }
        let Some(worker) = session.worker.as_mut() else {
            return Err("the Mitsuba process is not running".into());
        };
        let result = exchange(worker, &header, rays, n * per_ray);
        if let Err(e) = &result {
            let message = format!("Mitsuba failed: {e}{}", log_tail(&self.log_path()));
            if let Some(w) = session.worker.take() {
                close(w, false);
            }
            session.failure = Some(message.clone());
            return Err(message);
        }
        result
    }

    fn log_path(&self) -> PathBuf {
        self.dir.path().join("mitsuba.log")
    }

    /// World rays of a camera at `world_from_camera`, relative to the export offset,
    /// 6 floats each; invalid (zero) rays become a harmless ray whose result is
    /// ignored. Also says which rays are valid.
    fn ray_buffer(&self, world_from_camera: &Pose, rays: &[[f32; 3]]) -> (Vec<f32>, Vec<bool>) {
        let mut buf = Vec::with_capacity(6 * rays.len());
        let mut valid = Vec::with_capacity(rays.len());
        let origin = world_from_camera.translation.vector - self.scene.offset;
        for r in rays {
            let ray = world_ray(world_from_camera, r);
            valid.push(ray.is_some());
            let d = ray.map_or(nalgebra::Vector3::z(), |r| r.dir);
            buf.extend_from_slice(&[
                origin.x as f32,
                origin.y as f32,
                origin.z as f32,
                d.x as f32,
                d.y as f32,
                d.z as f32,
            ]);
        }
        (buf, valid)
    }

    /// Mitsuba's nearest hit along each ray (`rays` in the camera frame, zero =
    /// invalid) for a camera at `world_from_camera`.
    pub fn trace(
        &self,
        world_from_camera: &Pose,
        rays: &[[f32; 3]],
    ) -> Result<Vec<Option<MitsubaHit>>, String> {
        let (buf, valid) = self.ray_buffer(world_from_camera, rays);
        let out = self.request(json!({"op": "echoes"}), &buf, 6)?;
        out.chunks_exact(6)
            .zip(valid)
            .map(|(e, valid)| {
                let t = f64::from(e[0]);
                if !(valid && t.is_finite() && t > 0.0) {
                    return Ok(None);
                }
                let index = e[2] as usize;
                let &(object, material) = self.scene.shapes.get(index).ok_or_else(|| {
                    format!(
                        "Mitsuba reported shape {index} of {}",
                        self.scene.shapes.len()
                    )
                })?;
                Ok(Some(MitsubaHit {
                    distance_m: t,
                    cos_incidence: f64::from(e[1]).clamp(0.0, 1.0),
                    object,
                    material,
                    albedo: [e[3], e[4], e[5]],
                }))
            })
            .collect()
    }

    /// Lidar echoes: Mitsuba's nearest hit along each ray, with the material's lidar
    /// reflectivity (else the luminance of the albedo at the hit, point-sampled).
    pub fn echoes(
        &self,
        world_from_camera: &Pose,
        rays: &[[f32; 3]],
    ) -> Result<Vec<Option<SurfaceSample>>, String> {
        Ok(self
            .trace(world_from_camera, rays)?
            .into_iter()
            .map(|hit| {
                hit.map(|h| SurfaceSample {
                    range_m: h.distance_m,
                    cos_incidence: h.cos_incidence,
                    reflectivity: self
                        .reflectivity
                        .get(h.material as usize)
                        .copied()
                        .flatten()
                        .unwrap_or_else(|| luminance(h.albedo)),
                    object: h.object,
                })
            })
            .collect())
    }

    /// Linear radiance along each ray: direct light (paths of 2 segments, one sample:
    /// exact for point and directional lights) or `gi`'s path tracing, plus the
    /// ambient term at the first hit; the background where nothing is hit.
    pub fn radiance(
        &self,
        world_from_camera: &Pose,
        rays: &[[f32; 3]],
        specular: Option<f32>,
        gi: Option<&GlobalIllumination>,
    ) -> Result<Vec<Rgb>, String> {
        let (buf, valid) = self.ray_buffer(world_from_camera, rays);
        let (max_depth, spp) = gi.map_or((2, 1), |g| (g.max_depth, g.samples_per_pixel));
        // Path-tracing noise keyed by the pose: deterministic, different per frame.
        let t = world_from_camera.translation.vector;
        let q = world_from_camera.rotation.coords;
        let seed = [t.x, t.y, t.z, q.x, q.y, q.z, q.w]
            .iter()
            .fold(0u64, |h, v| mix64(h ^ v.to_bits()));
        let header = json!({
            "op": "radiance",
            "specular": specular.filter(|s| *s > 0.0),
            "max_depth": max_depth,
            "spp": spp,
            "seed": seed & 0xFFFF_FFFF,
        });
        let out = self.request(header, &buf, 3)?;
        Ok(out
            .chunks_exact(3)
            .zip(valid)
            .map(|(c, valid)| {
                if valid && c.iter().all(|v| v.is_finite()) {
                    [c[0].max(0.0), c[1].max(0.0), c[2].max(0.0)]
                } else {
                    [0.0; 3]
                }
            })
            .collect())
    }
}

/// Sends one request and reads its reply of `expect` floats.
fn exchange(
    worker: &mut Worker,
    header: &serde_json::Value,
    rays: &[f32],
    expect: usize,
) -> Result<Vec<f32>, String> {
    let mut bytes = Vec::with_capacity(4 * rays.len() + 256);
    bytes.extend_from_slice(header.to_string().as_bytes());
    bytes.push(b'\n');
    for v in rays {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    worker
        .stdin
        .write_all(&bytes)
        .and_then(|()| worker.stdin.flush())
        .map_err(|e| format!("writing to the Mitsuba process: {e}"))?;
    let reply = read_line(&mut worker.stdout)?;
    if reply.get("ok").and_then(|v| v.as_bool()) != Some(true) {
        return Err(error_text(&reply));
    }
    let floats = reply.get("floats").and_then(|v| v.as_u64()).unwrap_or(0);
    if floats != expect as u64 {
        return Err(format!("{floats} values in a reply, expected {expect}"));
    }
    let mut payload = vec![0u8; 4 * expect];
    worker
        .stdout
        .read_exact(&mut payload)
        .map_err(|e| format!("reading from the Mitsuba process: {e}"))?;
    Ok(payload
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect())
}

/// Ends the process: closes its input (it exits at end of input) and waits up to
/// [`EXIT_GRACE`] when `graceful`, then kills it if it is still running.
fn close(worker: Worker, graceful: bool) {
    let Worker {
        mut child,
        stdin,
        stdout,
    } = worker;
    drop(stdin);
    drop(stdout);
    let deadline = Instant::now() + if graceful { EXIT_GRACE } else { Duration::ZERO };
    loop {
        match child.try_wait() {
            Ok(Some(_)) => return,
            Ok(None) if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(20)),
            _ => {
                let _ = child.kill();
                let _ = child.wait();
                return;
            }
        }
    }
}

fn log_tail(path: &Path) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let lines: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty()).collect();
    if lines.is_empty() {
        return String::new();
    }
    let tail = &lines[lines.len().saturating_sub(12)..];
    format!("\nMitsuba's log ends with:\n{}", tail.join("\n"))
}

impl Drop for MitsubaRenderer {
    fn drop(&mut self) {
        let worker = match self.session.get_mut() {
            Ok(s) => s.worker.take(),
            Err(p) => p.into_inner().worker.take(),
        };
        if let Some(w) = worker {
            close(w, true);
        }
    }
}

/// A view of a [`MitsubaRenderer`] as a [`RenderBackend`], with or without global
/// illumination (the effected and the clean renders share one process).
#[derive(Debug, Clone)]
pub struct MitsubaBackend {
    renderer: Arc<MitsubaRenderer>,
    gi: Option<GlobalIllumination>,
}

impl MitsubaBackend {
    pub fn new(renderer: Arc<MitsubaRenderer>, gi: Option<GlobalIllumination>) -> Self {
        Self { renderer, gi }
    }

    pub fn renderer(&self) -> &Arc<MitsubaRenderer> {
        &self.renderer
    }
}

impl RenderBackend for MitsubaBackend {
    fn name(&self) -> &'static str {
        "mitsuba"
    }

    fn echoes(
        &self,
        world_from_camera: &Pose,
        rays: &[[f32; 3]],
        _beam_rad: f64,
    ) -> Vec<Option<SurfaceSample>> {
        // A failure is kept by the renderer and reported by `failure`.
        self.renderer
            .echoes(world_from_camera, rays)
            .unwrap_or_else(|_| vec![None; rays.len()])
    }

    fn radiance(
        &self,
        world_from_camera: &Pose,
        rays: &CameraRays,
        specular: Option<f32>,
    ) -> Vec<Rgb> {
        self.renderer
            .radiance(world_from_camera, &rays.rays, specular, self.gi.as_ref())
            .unwrap_or_else(|_| vec![[0.0; 3]; rays.rays.len()])
    }

    fn failure(&self) -> Option<String> {
        self.renderer.failure()
    }
}
