//! `texel-bench web`: the field display measured. An in-process daemon on the
//! simulated `lab` orbit serves the page built by `scripts/build-web.sh`; headless
//! Chromium (`scripts/node/web-view.mjs`, WebGPU on SwiftShader, then WebGL2 on
//! SwiftShader through ANGLE) opens the whole model's overview; the native renderer
//! (lavapipe) draws the same view. Reported: the wasm's size (raw and gzip), page
//! load to the full model on screen (first load, and with the wasm cached: the page
//! left for `about:blank` and opened again), where the cached load's time went step
//! by step (`data-texel-load`), the frame time in the browser on each path against
//! the native frame time (the browser's is the interval between frames drawn one
//! after the other while a drag moves the view, which never goes below the display's
//! 16.7 ms), and the bytes a browser receives per scan.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use texel_daemon::config::SessionConfig;
use texel_daemon::pipeline::Session;
use texel_viewer::composite::Mode;
use texel_viewer::live::fetch::fetch_model;
use texel_viewer::live::snapshots::orbit_pose;
use tokio_util::sync::CancellationToken;

use crate::live_viewer::{self, HEIGHT, WIDTH};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Scans in the model: the first frames of the `lab` orbit.
    #[arg(long, default_value_t = 36)]
    pub frames: usize,
    /// Native frames timed.
    #[arg(long, default_value_t = 30)]
    pub native_frames: u32,
    /// The repository root (default: the current directory).
    #[arg(long, default_value = ".")]
    pub repo: PathBuf,
}

/// What one browser run reported.
#[derive(Debug)]
struct BrowserRun {
    path: String,
    first_ready_ms: f64,
    cached_ready_ms: f64,
    /// The cached load's steps (`data-texel-load`, `crate::web::load` in the viewer).
    cached_load: serde_json::Value,
    /// When the page's own files came (resource timing).
    cached_files: serde_json::Value,
    frame_ms: f64,
    bytes: f64,
    scans: f64,
}

pub fn run(args: &Args) -> Result<()> {
    if args.frames == 0 {
        bail!("--frames must be positive");
    }
    let repo = args.repo.canonicalize().context("--repo")?;
    let web_dir = repo.join("target/web");
    let wasm = web_dir.join("texel_viewer_web_bg.wasm");
    if !web_dir.join("index.html").exists() || !wasm.exists() {
        bail!(
            "the browser viewer is not built in {}: run `bash scripts/build-web.sh`",
            web_dir.display()
        );
    }
    // 1. The page's size.
    let wasm_bytes = std::fs::metadata(&wasm)?.len();
    let gzip = Command::new("gzip").arg("-9c").arg(&wasm).output()?;
    if !gzip.status.success() {
        bail!("gzip failed on {}", wasm.display());
    }
    let js_bytes = std::fs::metadata(web_dir.join("texel_viewer_web.js"))?.len();

    // 2. The daemon, its model complete.
    let work = std::env::temp_dir().join(format!("texel-bench-web-{}", std::process::id()));
    std::fs::create_dir_all(&work)?;
    let toml = session_toml(&repo, &web_dir, args.frames);
    let config = SessionConfig::from_toml_str(&toml, "texel-bench web")?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let shutdown = CancellationToken::new();
    let session = runtime.block_on(Session::start(config, shutdown.clone()))?;
    let addr = session.local_addr.context("the session does not serve")?;
    let model = fetch_model(&addr.to_string(), "", args.frames, Duration::from_secs(900))?;
    eprintln!("web: the daemon's model holds {} scans", model.len());
    // The view: the whole model from outside it (the live viewer benchmark's overview).
    let pose = orbit_pose(&model, 0).context("the model has no scans")?;
    let query = texel_viewer::web::view_query(Mode::Blended, 4, &pose, 50.0);
    let url = format!("http://{addr}/{query}&ready={}", args.frames);

    // 3. The browser on each path, then the native renderer on the same view.
    let mut runs = Vec::new();
    for backend in ["webgpu", "webgl2"] {
        let shot = work.join(format!("{backend}.png"));
        runs.push(browser_run(&repo, &url, &shot, backend)?);
    }
    let native = live_viewer::measure_on_daemon(addr, 768, args.native_frames)?;
    let native_ms = native
        .iter()
        .find(|v| v.view == "overview")
        .map(|v| v.frame_ms)
        .context("no overview figures")?;
    shutdown.cancel();
    drop(session);
    drop(runtime);
    let _ = std::fs::remove_dir_all(&work);

    // 4. The report.
    println!("## The field display (`texel-bench web`)\n");
    println!(
        "Model: the `lab` orbit's first {} scans, JPEG textures as served; view: the \
         whole model from outside it, {WIDTH}x{HEIGHT}, blended, k = 4.\n",
        args.frames
    );
    println!(
        "wasm: {:.2} MB, {:.2} MB gzip -9; JavaScript glue {:.0} kB\n",
        wasm_bytes as f64 / 1e6,
        gzip.stdout.len() as f64 / 1e6,
        js_bytes as f64 / 1e3
    );
    println!(
        "| path | load to full model, first (ms) | load to full model, wasm cached (ms) \
         | frame (ms) | frame / native | bytes per scan |"
    );
    println!("|---|---|---|---|---|---|");
    for r in &runs {
        println!(
            "| {} | {:.0} | {:.0} | {:.1} | {:.2} | {:.0} |",
            r.path,
            r.first_ready_ms,
            r.cached_ready_ms,
            r.frame_ms,
            r.frame_ms / native_ms.max(1e-3),
            r.bytes / r.scans.max(1.0)
        );
    }
    println!(
        "| native viewer, lavapipe (residency step and render, median of {}) | — | — | \
         {native_ms:.1} | 1.00 | — |",
        args.native_frames
    );
    print_breakdown(&runs);
    Ok(())
}

/// The cached load step by step: when each step was reached (ms after navigation),
/// then the frame loop's time until ready.
fn print_breakdown(runs: &[BrowserRun]) {
    const STEPS: [(&str, &str); 11] = [
        ("html", "page received"),
        ("wasmFile", "wasm received"),
        ("wasm", "wasm started"),
        ("gpu", "GPU device"),
        ("pipelines", "renderer and pipelines"),
        ("socket", "WebSocket open"),
        ("snapshot", "snapshot received"),
        ("fetched", "all scans fetched"),
        ("resident", "all scans resident"),
        ("firstFrame", "first frame drawn"),
        ("ready", "ready"),
    ];
    println!("\nThe cached load, ms after navigation:\n");
    let names: Vec<&str> = STEPS.iter().map(|(_, name)| *name).collect();
    println!(
        "| path | {} | decoding (ms) | residency steps (ms) | drawing (ms) | frames drawn |",
        names.join(" | ")
    );
    println!("|---|{}---|---|---|---|", "---|".repeat(STEPS.len()));
    for r in runs {
        let at = |key: &str| {
            let value = match key {
                "html" => &r.cached_files["html"]["end"],
                "wasmFile" => &r.cached_files["wasm"]["end"],
                _ => &r.cached_load[key],
            };
            value
                .as_f64()
                .map_or_else(|| "—".to_string(), |v| format!("{v:.0}"))
        };
        let steps: Vec<String> = STEPS.iter().map(|(key, _)| at(key)).collect();
        println!(
            "| {} | {} | {} | {} | {} | {} |",
            r.path,
            steps.join(" | "),
            at("pumpMs"),
            at("uploadMs"),
            at("drawMs"),
            at("frames")
        );
    }
}

fn session_toml(repo: &Path, web_dir: &Path, frames: usize) -> String {
    let scene = repo.join("configs/scenes/lab.toml");
    format!(
        "[session]\nname = \"bench-web\"\nexit_when_sources_end = false\n\
         [[source.sim]]\nscene = {scene:?}\nseed = 1\nframes = {frames}\nspeed = 1.0\n\
         fast = true\nlate = \"wait\"\ntruth = true\n\
         [pipeline]\noverload = \"backpressure\"\n\
         [serve]\nbind = \"127.0.0.1:0\"\nweb_dir = {web_dir:?}\n\
         [model.retirement]\nenabled = false\n"
    )
}

/// Runs `web-view.mjs` on `url` with `backend` and reads its report.
fn browser_run(repo: &Path, url: &str, shot: &Path, backend: &str) -> Result<BrowserRun> {
    let node_dir = std::env::var_os("TEXEL_NODE_DIR").map_or_else(
        || {
            std::env::var_os("XDG_CACHE_HOME")
                .map(PathBuf::from)
                .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))
                .unwrap_or_default()
                .join("texel/node")
        },
        PathBuf::from,
    );
    if !node_dir.join("node_modules").exists() {
        bail!(
            "the Node.js peer tools are missing at {}: run scripts/setup.sh",
            node_dir.display()
        );
    }
    // The script resolves playwright from its own folder: a copy beside the packages.
    let copy = node_dir.join(format!(".bench-{}-web-view.mjs", std::process::id()));
    std::fs::copy(repo.join("scripts/node/web-view.mjs"), &copy)?;
    let out = Command::new("node")
        .arg(&copy)
        .arg(url)
        .arg(shot)
        .args([WIDTH.to_string(), HEIGHT.to_string()])
        .args(["--backend", backend])
        .output();
    let _ = std::fs::remove_file(&copy);
    let out = out.context("running node")?;
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).with_context(|| {
        format!(
            "web-view.mjs ({backend}) said: {}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        )
    })?;
    eprintln!("web: {backend}, the cached load: {}", report["cached"]);
    let errors = report["errors"].as_array().cloned().unwrap_or_default();
    if !errors.is_empty() {
        bail!("the page ({backend}) reported errors: {errors:?}");
    }
    let number = |section: &str, key: &str| report[section][key].as_f64().unwrap_or(f64::NAN);
    Ok(BrowserRun {
        path: short_path(report["cached"]["path"].as_str().unwrap_or(backend)),
        first_ready_ms: number("first", "readyMs"),
        cached_ready_ms: number("cached", "readyMs"),
        cached_load: report["cached"]["load"].clone(),
        cached_files: report["cached"]["files"].clone(),
        frame_ms: number("steady", "frameMs"),
        bytes: number("cached", "bytes"),
        scans: number("cached", "scans"),
    })
}

/// "WebGL2 (ANGLE (...)) · naive layers (...)" as "WebGL2 · naive layers".
fn short_path(path: &str) -> String {
    path.split(" · ")
        .map(|part| part.split(" (").next().unwrap_or(part))
        .collect::<Vec<_>>()
        .join(" · ")
}
