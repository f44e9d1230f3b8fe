//! Helpers shared by the end-to-end tests in `tests/tests/`: where the repository,
//! its scripts and the Python venv of peer tools are.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The repository root.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."))
}

/// The venv that `scripts/setup.sh` creates: `$TEXEL_VENV`, else
/// `$XDG_CACHE_HOME/texel/venv`, else `~/.cache/texel/venv`.
pub fn venv_dir() -> PathBuf {
    std::env::var_os("TEXEL_VENV").map_or_else(|| texel_cache().join("venv"), PathBuf::from)
}

/// Where `scripts/setup.sh` keeps the peer tools: `$XDG_CACHE_HOME/texel`, else
/// `~/.cache/texel`.
fn texel_cache() -> PathBuf {
    std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))
        .unwrap_or_else(|| PathBuf::from(".cache"))
        .join("texel")
}

/// The venv's Python. Panics with the set-up command when it is missing: the
/// interop tests are part of the suite, not optional.
pub fn python() -> PathBuf {
    let python = venv_dir().join("bin").join("python");
    assert!(
        python.exists(),
        "the Python venv with the peer tools is missing at {}; run scripts/setup.sh \
         (the README's test command does this)",
        python.display()
    );
    python
}

/// Runs `scripts/python/<script>` with the venv's Python; panics with its stderr if
/// it fails.
pub fn run_python(script: &str, args: &[&std::ffi::OsStr]) -> Output {
    let path = repo_root().join("scripts").join("python").join(script);
    let output = Command::new(python())
        .arg(&path)
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("cannot run {}: {e}", path.display()));
    assert!(
        output.status.success(),
        "{script} failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    output
}

/// The Node.js peer checks that `scripts/setup.sh` installs: `$TEXEL_NODE_DIR`, else
/// `$XDG_CACHE_HOME/texel/node`, else `~/.cache/texel/node`.
pub fn node_dir() -> PathBuf {
    std::env::var_os("TEXEL_NODE_DIR").map_or_else(|| texel_cache().join("node"), PathBuf::from)
}

/// Panics with the set-up command when the Node.js packages are missing.
fn assert_node_modules() {
    let modules = node_dir().join("node_modules");
    assert!(
        modules.exists(),
        "the Node.js peer checks are missing at {}; run scripts/setup.sh (the README's \
         test command does this)",
        modules.display()
    );
}

/// Runs `scripts/node/<script>` with Node.js, its packages resolved from
/// [`node_dir`]; panics with the set-up command when they are missing and with the
/// script's stderr when it fails.
pub fn run_node(script: &str, args: &[&std::ffi::OsStr]) -> Output {
    assert_node_modules();
    // An ES module resolves packages from its own folder upwards, so the script runs
    // from a copy beside the installed packages.
    // One copy per call, so tests running at once never read a half-written one.
    static CALLS: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    let call = CALLS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let source = repo_root().join("scripts").join("node").join(script);
    let copy = node_dir().join(format!(".{}-{call}-{script}", std::process::id()));
    std::fs::copy(&source, &copy)
        .unwrap_or_else(|e| panic!("cannot copy {} beside its packages: {e}", source.display()));
    let output = Command::new("node").arg(&copy).args(args).output();
    let _ = std::fs::remove_file(&copy);
    let output = output.unwrap_or_else(|e| panic!("cannot run node {script}: {e}"));
    assert!(
        output.status.success(),
        "{script} failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    output
}

/// A Node.js peer script running beside the test, its stdin and stdout piped (for
/// scripts the test talks to while they run); the script's copy is removed on drop.
pub struct NodeChild {
    pub child: std::process::Child,
    copy: PathBuf,
}

impl Drop for NodeChild {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_file(&self.copy);
    }
}

/// Starts `node SCRIPT ARGS` like [`run_node`] but without waiting for it.
pub fn spawn_node(script: &str, args: &[&std::ffi::OsStr]) -> NodeChild {
    assert_node_modules();
    let source = repo_root().join("scripts").join("node").join(script);
    let copy = node_dir().join(format!(".{}-spawned-{script}", std::process::id()));
    std::fs::copy(&source, &copy)
        .unwrap_or_else(|e| panic!("cannot copy {} beside its packages: {e}", source.display()));
    let child = Command::new("node")
        .arg(&copy)
        .args(args)
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot run node {script}: {e}"));
    NodeChild { child, copy }
}

/// The path of a binary of this workspace, built by cargo for the tests.
pub fn workspace_binary(name: &str) -> PathBuf {
    // Integration tests run from target/<profile>/deps; binaries sit one level up.
    let exe = std::env::current_exe().unwrap_or_default();
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .map(Path::to_path_buf)
        .unwrap_or_default();
    dir.join(name)
}

/// Small captures of an analytic scene, written with the project's own capture
/// writer, for tests of the daemon's pipeline.
mod texeld;
pub use texeld::Texeld;

pub mod captures {
    use std::path::Path;

    use nalgebra::Vector2;
    use texel::capture::{CaptureWriter, EoEncoding, PoseTopic, RangeEncoding, WriterOptions};
    use texel::pose::pose_from_parts;
    use texel::{EoFrame, PinholeCamera, Pose, RangeFrame, RangeNoise, SensorModel};

    /// A 16x12 lidar and a 64x48 EO camera, 2 cm apart.
    pub fn sensor() -> SensorModel {
        SensorModel {
            name: "analytic".into(),
            lidar: PinholeCamera::from_vertical_fov(16, 12, 30.0)
                .unwrap_or_else(|e| panic!("lidar model: {e}")),
            eo: PinholeCamera::from_vertical_fov(64, 48, 40.0)
                .unwrap_or_else(|e| panic!("EO model: {e}")),
            eo_from_lidar: pose_from_parts([0.02, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
                .unwrap_or_else(|e| panic!("extrinsic: {e}")),
            range_noise: RangeNoise {
                sigma_m: 0.005,
                sigma_per_m: 0.0,
            },
            range_bias_m: 0.0,
            min_range_m: 0.3,
            max_range_m: 30.0,
            eo_response: None,
        }
    }

    /// Frame `i` at `timestamp_ns`: a wall `3 + 0.01 i` m away with a box at 2 m
    /// over the left third; the EO image a colour ramp that changes with `i`.
    pub fn frame(m: &SensorModel, i: u32, timestamp_ns: u64) -> (RangeFrame, EoFrame) {
        let (w, h) = (m.lidar.width, m.lidar.height);
        let mut r = RangeFrame::empty(w, h, timestamp_ns, i);
        for v in 0..h {
            for u in 0..w {
                let ray = m
                    .lidar
                    .unproject_ray(Vector2::new(f64::from(u), f64::from(v)))
                    .unwrap_or_else(|e| panic!("ray: {e}"));
                let depth = if u < w / 3 {
                    2.0
                } else {
                    3.0 + 0.01 * f64::from(i)
                };
                r.ranges_m[(v * w + u) as usize] = (depth / ray.z) as f32;
            }
        }
        let (ew, eh) = (m.eo.width, m.eo.height);
        let mut rgb = Vec::with_capacity((ew * eh * 3) as usize);
        for v in 0..eh {
            for u in 0..ew {
                rgb.extend_from_slice(&[
                    (u * 4) as u8,
                    (v * 5) as u8,
                    (i.wrapping_mul(17) % 256) as u8,
                ]);
            }
        }
        let eo = EoFrame {
            width: ew,
            height: eh,
            rgb,
            timestamp_ns,
            exposure: None,
        };
        (r, eo)
    }

    /// The pose of frame `i`: walking along +x, turning slowly about z.
    pub fn pose(i: u32) -> Pose {
        let angle = 0.01 * f64::from(i);
        pose_from_parts(
            [0.1 * f64::from(i), 0.0, 1.5],
            [0.0, 0.0, (angle / 2.0).sin(), (angle / 2.0).cos()],
        )
        .unwrap_or_else(|e| panic!("pose: {e}"))
    }

    /// The timestamp of frame `i` for a capture starting at 1 s with `period_ns`.
    pub fn timestamp(i: u32, period_ns: u64) -> u64 {
        1_000_000_000 + u64::from(i) * period_ns
    }

    /// Writes `frames` texel frames `period_ns` apart, each with its pose on `poses`
    /// (none when `None`).
    pub fn write(path: &Path, frames: u32, period_ns: u64, poses: Option<PoseTopic>) {
        write_with(path, &sensor(), frames, period_ns, poses);
    }

    /// As [`write`], with a given sensor model.
    pub fn write_with(
        path: &Path,
        m: &SensorModel,
        frames: u32,
        period_ns: u64,
        poses: Option<PoseTopic>,
    ) {
        write_with_options(path, m, frames, period_ns, poses, WriterOptions::default());
    }

    /// As [`write`], in chunks of about `chunk_size_bytes` (small chunks give damage
    /// somewhere to land without taking the whole capture).
    pub fn write_chunked(
        path: &Path,
        frames: u32,
        period_ns: u64,
        poses: Option<PoseTopic>,
        chunk_size_bytes: u64,
    ) {
        let options = WriterOptions {
            chunk_size_bytes,
            ..WriterOptions::default()
        };
        write_with_options(path, &sensor(), frames, period_ns, poses, options);
    }

    fn write_with_options(
        path: &Path,
        m: &SensorModel,
        frames: u32,
        period_ns: u64,
        poses: Option<PoseTopic>,
        options: WriterOptions,
    ) {
        let mut w = CaptureWriter::create(path, options).unwrap_or_else(|e| panic!("{e}"));
        w.write_sensor(m, timestamp(0, period_ns))
            .unwrap_or_else(|e| panic!("{e}"));
        for i in 0..frames {
            let t = timestamp(i, period_ns);
            let (r, eo) = frame(m, i, t);
            w.write_range(&r, RangeEncoding::F32Metres)
                .unwrap_or_else(|e| panic!("{e}"));
            w.write_eo(&eo, EoEncoding::Rgb8)
                .unwrap_or_else(|e| panic!("{e}"));
            if let Some(topic) = poses {
                w.write_pose(topic, t, &pose(i))
                    .unwrap_or_else(|e| panic!("{e}"));
            }
        }
        w.finish().unwrap_or_else(|e| panic!("{e}"));
    }
}
