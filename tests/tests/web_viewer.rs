//! The field display in a real browser: `texeld` on the simulator serves the page
//! (built by `scripts/build-web.sh`) and the wire protocol over WebSocket on its viewer
//! port; headless Chromium (WebGPU on SwiftShader, driven by `scripts/node/web-view.mjs`)
//! opens a deep-linked view and waits until the page says the model is drawn; its
//! screenshot is compared with `texel-viewer render --connect` of the same view and
//! mode (lavapipe, the k-buffer), on WebGPU (the k-buffer too) and on WebGL2 (no
//! storage buffers: the naive layers). On both paths the page must draw nothing while
//! idle and draw while the hand drags the view. Then the daemon is killed and started
//! again on the same port: the page must reconnect by itself and draw the new daemon's
//! model.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use texel_e2e::{Texeld, repo_root, spawn_node, workspace_binary};

/// Scans in the model: a short stretch of the `lab` orbit.
const FRAMES: usize = 6;
const WIDTH: u32 = 640;
const HEIGHT: u32 = 480;
const FOV_DEG: f64 = 50.0;
/// A pixel agrees when no channel differs by more than this (of 255): the two
/// rasterisers (SwiftShader, lavapipe) place triangle edges and round colours a little
/// differently.
const CHANNEL_TOLERANCE: u8 = 8;
/// At least this share of the pixels must agree.
const MIN_AGREEING_SHARE: f64 = 0.995;

fn session_file(dir: &Path, bind: &str) -> PathBuf {
    let path = dir.join(format!("web-{}.toml", bind.replace([':', '.'], "-")));
    let scene = repo_root().join("configs/scenes/lab.toml");
    let web_dir = repo_root().join("target/web");
    std::fs::write(
        &path,
        format!(
            "[session]\nname = \"web\"\nexit_when_sources_end = false\n\
             [[source.sim]]\nscene = {scene:?}\nseed = 5\nframes = {FRAMES}\n\
             lidar_size = [64, 48]\neo_size = [160, 120]\nspeed = 1.0\nfast = true\n\
             late = \"wait\"\ntruth = true\nrender_threads = 1\n\
             [pipeline]\noverload = \"backpressure\"\n\
             [serve]\nbind = \"{bind}\"\ntexture = \"png\"\nweb_dir = {web_dir:?}\n\
             [status]\ninterval_ms = 500\n\
             [model.retirement]\nenabled = false\n"
        ),
    )
    .unwrap();
    path
}

/// Share of pixels whose channels all lie within the tolerance, and the shares of
/// pixels either image draws (not background); the share of identical pixels is
/// printed.
fn agreement(a: &image::RgbaImage, b: &image::RgbaImage) -> (f64, f64, f64) {
    assert_eq!(a.dimensions(), b.dimensions());
    let (mut agree, mut same, mut drawn_a, mut drawn_b) = (0usize, 0usize, 0usize, 0usize);
    for (p, q) in a.pixels().zip(b.pixels()) {
        let close = (0..3).all(|c| p[c].abs_diff(q[c]) <= CHANNEL_TOLERANCE);
        agree += usize::from(close);
        same += usize::from((0..3).all(|c| p[c] == q[c]));
        drawn_a += usize::from(p[0].max(p[1]).max(p[2]) > 8);
        drawn_b += usize::from(q[0].max(q[1]).max(q[2]) > 8);
    }
    let n = (a.width() * a.height()) as f64;
    println!("identical pixels: {:.2} %", 100.0 * same as f64 / n);
    (agree as f64 / n, drawn_a as f64 / n, drawn_b as f64 / n)
}

/// Keeps an image for a look when a comparison fails (target/ is git-ignored).
fn keep(image: &image::RgbaImage, name: &str) {
    let kept = repo_root().join("target/web-viewer-test");
    if std::fs::create_dir_all(&kept).is_ok() {
        let _ = image.save(kept.join(name));
    }
}

#[test]
fn the_browser_draws_what_render_draws_and_reconnects_after_a_restart() {
    let web = repo_root().join("target/web/index.html");
    assert!(
        web.exists(),
        "the browser viewer is not built ({} is missing): run `bash scripts/build-web.sh` \
         (the README's test command does)",
        web.display()
    );
    let dir = tempfile::tempdir().unwrap();
    let mut daemon = Texeld::start(&session_file(dir.path(), "127.0.0.1:0"));
    let addr = daemon.wait_for("serving viewers on ");
    let url = daemon.wait_for("field display: ");
    assert_eq!(
        url,
        format!("http://{addr}/"),
        "the page's address names the port"
    );

    // The view: behind and above the middle scan's acquisition pose.
    let model = texel_viewer::live::fetch::fetch_model(&addr, "", FRAMES, Duration::from_secs(180))
        .unwrap();
    let middle = &model.scans()[FRAMES / 2];
    let back = nalgebra::Translation3::new(0.1, -0.15, -0.6);
    let world_from_eo = middle.world_from_scan
        * nalgebra::Isometry3::from_parts(back, nalgebra::UnitQuaternion::identity());
    let mode = texel_viewer::composite::Mode::Blended;
    let query = texel_viewer::web::view_query(mode, 4, &world_from_eo, FOV_DEG);
    let t = world_from_eo.translation.vector;
    let q = world_from_eo.rotation.coords;
    let pose = format!("{} {} {} {} {} {} {}", t.x, t.y, t.z, q.x, q.y, q.z, q.w);

    // The native renderer's image of the view.
    let reference = dir.path().join("render.png");
    let out = Command::new(workspace_binary("texel-viewer"))
        .args([
            "render",
            "--connect",
            &addr,
            "--wait-scans",
            &FRAMES.to_string(),
        ])
        .args([
            "--pose",
            &pose,
            "--mode",
            mode.name(),
            "--fov-deg",
            &FOV_DEG.to_string(),
        ])
        .args([
            "--width",
            &WIDTH.to_string(),
            "--height",
            &HEIGHT.to_string(),
        ])
        .arg("--out")
        .arg(&reference)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "texel-viewer render: {}",
        String::from_utf8_lossy(&out.stderr)
    );

    // WebGL2 first: no storage buffers, so the page composites with the naive layers.
    let gl_shot = dir.path().join("browser-webgl2.png");
    let page = format!("{url}{query}&ready={FRAMES}");
    let out = texel_e2e::run_node(
        "web-view.mjs",
        &[
            page.as_ref(),
            gl_shot.as_os_str(),
            WIDTH.to_string().as_ref(),
            HEIGHT.to_string().as_ref(),
            "--backend".as_ref(),
            "webgl2".as_ref(),
        ],
    );
    let gl_report: serde_json::Value = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("web-view.mjs said {:?}: {e}", out.stdout));
    println!("web-view report (WebGL2): {gl_report}");
    let gl_errors = gl_report["errors"].as_array().cloned().unwrap_or_default();
    assert!(
        gl_errors.is_empty(),
        "the WebGL2 page reported errors: {gl_errors:?}"
    );
    assert!(
        gl_report["cached"]["path"]
            .as_str()
            .is_some_and(|p| p.starts_with("WebGL2") && p.contains("naive layers")),
        "the page did not say it composites with the naive layers on WebGL2: {gl_report}"
    );
    assert_paced(&gl_report);
    let native = image::open(&reference).unwrap().to_rgba8();
    let gl = image::open(&gl_shot).unwrap().to_rgba8();
    let (share, drawn_gl, drawn_native) = agreement(&gl, &native);
    println!(
        "browser (WebGL2, naive layers) vs render: {:.2} % of pixels within \
         {CHANNEL_TOLERANCE}/255; drawn {:.1} % (browser), {:.1} % (render)",
        100.0 * share,
        100.0 * drawn_gl,
        100.0 * drawn_native
    );
    keep(&gl, "browser-webgl2.png");
    assert!(
        share >= MIN_AGREEING_SHARE,
        "the WebGL2 page's image differs from render's: {:.2} % agree",
        100.0 * share
    );

    // WebGPU, the k-buffer as natively.
    let shot = dir.path().join("browser.png");
    let mut node = spawn_node(
        "web-view.mjs",
        &[
            page.as_ref(),
            shot.as_os_str(),
            WIDTH.to_string().as_ref(),
            HEIGHT.to_string().as_ref(),
            "--restart-wait-ms".as_ref(),
            "120000".as_ref(),
        ],
    );
    let stdout = node.child.stdout.take().unwrap();
    let mut reports = BufReader::new(stdout).lines();
    let first = reports.next().and_then(Result::ok).unwrap_or_default();
    let first: serde_json::Value =
        serde_json::from_str(&first).unwrap_or_else(|e| panic!("web-view.mjs said {first:?}: {e}"));
    assert!(
        first.get("screenshot").is_some(),
        "the page never became ready: {first}"
    );

    let browser = image::open(&shot).unwrap().to_rgba8();
    keep(&browser, "browser-webgpu.png");
    keep(&native, "render.png");
    let (share, drawn_browser, drawn_native) = agreement(&browser, &native);
    println!(
        "browser vs render: {:.2} % of pixels within {CHANNEL_TOLERANCE}/255; drawn {:.1} % \
         (browser), {:.1} % (render)",
        100.0 * share,
        100.0 * drawn_browser,
        100.0 * drawn_native
    );
    assert!(drawn_native > 0.2, "the view shows too little of the model");
    assert!(
        share >= MIN_AGREEING_SHARE,
        "the browser's image differs from render's: {:.2} % agree",
        100.0 * share
    );

    // The daemon goes away and comes back on the same port: the page reconnects.
    let session = session_file(dir.path(), &addr);
    drop(daemon);
    let mut daemon = Texeld::start(&session);
    daemon.wait_for("serving viewers on ");
    let stdin = node.child.stdin.as_mut().unwrap();
    writeln!(stdin, "restarted").unwrap();
    stdin.flush().unwrap();
    let last = reports.next().and_then(Result::ok).unwrap_or_default();
    let report: serde_json::Value =
        serde_json::from_str(&last).unwrap_or_else(|e| panic!("web-view.mjs said {last:?}: {e}"));
    println!("web-view report: {report}");
    // A drag orbited the view: the address bar's deep link has a new pose, same mode.
    let (before, after) = (
        report["beforeDrag"].as_str().unwrap_or(""),
        report["afterDrag"].as_str().unwrap_or(""),
    );
    let pose_of = |q: &str| {
        texel_viewer::deep_link::DeepLink::parse(q)
            .ok()
            .and_then(|l| l.pose)
    };
    let (p0, p1) = (pose_of(before).unwrap(), pose_of(after).unwrap());
    assert!(
        p0.rotation.angle_to(&p1.rotation) > 0.05 && after.contains("mode=blended"),
        "a drag did not orbit the view: {before} -> {after}"
    );
    let errors = report["errors"].as_array().cloned().unwrap_or_default();
    assert!(errors.is_empty(), "the page reported errors: {errors:?}");
    assert_paced(&report);
    let after = &report["afterRestart"];
    assert!(
        after["connections"].as_u64().unwrap_or(0) >= 2,
        "the page did not reconnect: {after}"
    );
    assert!(
        after["ready"].as_u64().unwrap_or(0) >= FRAMES as u64,
        "the page did not draw the restarted daemon's model: {after}"
    );
    assert!(
        report["cached"]["path"]
            .as_str()
            .is_some_and(|p| p.starts_with("WebGPU")),
        "the page did not say it runs on WebGPU: {report}"
    );
}

/// The page draws only when something changed: no frame in two idle seconds after
/// the model is on screen, frames while a drag moves the view.
fn assert_paced(report: &serde_json::Value) {
    assert_eq!(
        report["idleFrames"].as_u64(),
        Some(0),
        "the page drew frames while nothing changed: {report}"
    );
    assert!(
        report["dragFrames"].as_u64().unwrap_or(0) > 0,
        "the page drew nothing while the view was dragged: {report}"
    );
}
