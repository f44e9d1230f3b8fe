//! Shared helpers of the viewer's GPU tests: one device per test binary (lavapipe in
//! CI; a missing adapter fails the test loudly), image comparison and golden files.
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use std::path::PathBuf;
use std::sync::OnceLock;

use texel::Pose;
use texel_viewer::camera::VirtualCamera;
use texel_viewer::gpu::{GpuContext, Renderer};
use texel_viewer::scenes;

pub fn gpu() -> &'static GpuContext {
    static GPU: OnceLock<GpuContext> = OnceLock::new();
    GPU.get_or_init(|| match GpuContext::headless() {
        Ok(g) => g,
        Err(e) => panic!("GPU tests need an adapter (CI installs lavapipe): {e}"),
    })
}

/// A renderer holding the box scene (3 scans), placed under `offset`.
pub fn box_renderer(offset: &Pose) -> Renderer {
    let sensor = scenes::test_sensor();
    let model = scenes::model_of(
        &scenes::box_scene(),
        &sensor,
        &scenes::box_scene_poses(),
        offset,
    );
    let mut r = Renderer::new(gpu());
    r.sync_model(&model).unwrap();
    r
}

/// The view the box-scene tests use: between the front and right scans.
pub fn box_camera(offset: &Pose) -> VirtualCamera {
    VirtualCamera::new(
        offset * scenes::look_at([0.9, -0.6, 0.2], [0.0, 0.0, 5.0]),
        55.0,
        160,
        120,
    )
    .unwrap()
}

/// Fraction of pixels whose every channel differs by at most `tol`.
pub fn fraction_within(a: &image::RgbaImage, b: &image::RgbaImage, tol: u8) -> f64 {
    assert_eq!(a.dimensions(), b.dimensions());
    let ok = a
        .pixels()
        .zip(b.pixels())
        .filter(|(p, q)| (0..3).all(|k| p[k].abs_diff(q[k]) <= tol))
        .count();
    ok as f64 / f64::from(a.width() * a.height())
}

pub fn golden_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/golden")
}

/// Compares with `tests/golden/NAME.png` (>= 99 % of pixels within 2/255 per channel);
/// writes NAME.actual.png and NAME.diff.png beside it on failure.
/// `TEXEL_UPDATE_GOLDEN=1` rewrites the golden instead.
pub fn check_golden(name: &str, actual: &image::RgbaImage) {
    let dir = golden_dir();
    let path = dir.join(format!("{name}.png"));
    if std::env::var_os("TEXEL_UPDATE_GOLDEN").is_some_and(|v| v == "1") {
        actual.save(&path).unwrap();
        return;
    }
    let golden = image::open(&path)
        .unwrap_or_else(|e| panic!("{}: {e} (TEXEL_UPDATE_GOLDEN=1 writes it)", path.display()))
        .to_rgba8();
    let within = fraction_within(&golden, actual, 2);
    if within < 0.99 {
        actual.save(dir.join(format!("{name}.actual.png"))).unwrap();
        let diff = image::RgbaImage::from_fn(actual.width(), actual.height(), |x, y| {
            let (p, q) = (golden.get_pixel(x, y), actual.get_pixel(x, y));
            let d = (0..3).map(|k| p[k].abs_diff(q[k])).max().unwrap_or(0);
            image::Rgba([d.saturating_mul(8), 0, 0, 255])
        });
        diff.save(dir.join(format!("{name}.diff.png"))).unwrap();
        panic!(
            "{name}: only {:.2} % of pixels within 2/255 of the golden",
            within * 100.0
        );
    }
}

/// Writes the box scene's three texel frames to a capture with poses on `topic`.
pub fn write_box_capture(path: &std::path::Path, topic: texel::capture::PoseTopic) {
    use texel::capture::{CaptureWriter, EoEncoding, RangeEncoding, WriterOptions};
    let sensor = scenes::test_sensor();
    let scene = scenes::box_scene();
    let mut w = CaptureWriter::create(path, WriterOptions::default()).unwrap();
    w.write_sensor(&sensor.model, 0).unwrap();
    for (i, pose) in scenes::box_scene_poses().iter().enumerate() {
        let (range, eo) =
            scenes::frames(&scene, &sensor, pose, scenes::tint(i as u32), i as u32 + 1);
        w.write_range(&range, RangeEncoding::F32Metres).unwrap();
        w.write_eo(&eo, EoEncoding::Rgb8).unwrap();
        w.write_pose(topic, range.timestamp_ns, pose).unwrap();
    }
    w.finish().unwrap();
}

pub fn viewer_binary() -> PathBuf {
    // The end-to-end tests (another package) share this module: there the binary is
    // the workspace's, beside the test executable's folder.
    match option_env!("CARGO_BIN_EXE_texel-viewer") {
        Some(path) => PathBuf::from(path),
        None => {
            let exe = std::env::current_exe().unwrap_or_default();
            let dir = exe.parent().and_then(std::path::Path::parent);
            dir.map(|d| d.join("texel-viewer")).unwrap_or_default()
        }
    }
}

/// An Xvfb server, killed when dropped.
pub struct Xvfb {
    child: std::process::Child,
    display: u32,
    /// Whether the display's files are this server's (it came up on it).
    owns_display: bool,
}

impl Drop for Xvfb {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        // A killed server leaves its lock file and socket behind: without this, every
        // run would use up a display number for good.
        if self.owns_display {
            remove_display_files(self.display);
        }
    }
}

fn lock_path(display: u32) -> String {
    format!("/tmp/.X{display}-lock")
}

fn socket_path(display: u32) -> String {
    format!("/tmp/.X11-unix/X{display}")
}

fn remove_display_files(display: u32) {
    let _ = std::fs::remove_file(lock_path(display));
    let _ = std::fs::remove_file(socket_path(display));
}

/// Whether `display`'s lock file names a process that is still running (a lock
/// that cannot be read counts as held).
fn display_in_use(display: u32) -> bool {
    let Ok(text) = std::fs::read_to_string(lock_path(display)) else {
        return std::path::Path::new(&lock_path(display)).exists();
    };
    match text.trim().parse::<u32>() {
        Ok(pid) => std::path::Path::new(&format!("/proc/{pid}")).exists(),
        Err(_) => true,
    }
}

/// Starts Xvfb on the first display number that no running server holds (a lock
/// left by a server that was killed is cleared first).
pub fn start_xvfb() -> (Xvfb, String) {
    // Tests of one binary run in parallel: one at a time picks a display and waits
    // for its server, so a second never clears the first's files as stale.
    static STARTING: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _starting = STARTING
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    for n in 90..140 {
        if display_in_use(n) {
            continue;
        }
        remove_display_files(n);
        let display = format!(":{n}");
        let child = std::process::Command::new("Xvfb")
            .args([&display, "-screen", "0", "800x600x24", "-nolisten", "tcp"])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .expect("Xvfb must be installed (scripts/setup.sh installs xvfb)");
        let mut xvfb = Xvfb {
            child,
            display: n,
            owns_display: false,
        };
        let start = std::time::Instant::now();
        while start.elapsed() < std::time::Duration::from_secs(10) {
            if std::path::Path::new(&socket_path(n)).exists() {
                xvfb.owns_display = true;
                return (xvfb, display);
            }
            // A server that lost the race for this display exits: try the next one.
            if matches!(xvfb.child.try_wait(), Ok(Some(_))) {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
    }
    panic!("no free X display for Xvfb");
}

/// Mean absolute error (0..255) of a render of the box scene against the scene's own
/// colours under `tint`, over the pixels the scene covers and the render coloured
/// (not the magenta background), and the share of the scene's pixels it coloured.
pub fn box_scene_error(
    image: &image::RgbaImage,
    camera: &VirtualCamera,
    tint: [f32; 3],
) -> (f64, f64) {
    let scene = scenes::box_scene();
    let eye = camera.centre_world();
    let (mut sum, mut n, mut hit) = (0.0, 0usize, 0usize);
    for y in 0..camera.height {
        for x in 0..camera.width {
            let dir = camera.world_from_eo.rotation * camera.pixel_ray_view(x, y);
            let Some((_, c)) = scene.cast(&eye, &dir) else {
                continue;
            };
            hit += 1;
            let px = image.get_pixel(x, y);
            if px.0[0..3] == [255, 0, 255] {
                continue;
            }
            n += 1;
            sum += (0..3)
                .map(|k| (f64::from(px[k]) - f64::from(c[k]) * f64::from(tint[k])).abs() / 3.0)
                .sum::<f64>();
        }
    }
    (sum / n.max(1) as f64, n as f64 / hit.max(1) as f64)
}
