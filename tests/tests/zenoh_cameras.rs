//! Many cameras, many viewers on Zenoh: two `texeld` processes, each a simulated
//! camera on the same scene (so in the same truth frame), publish on Zenoh on
//! loopback with explicit endpoints and no multicast scouting. Two `texel-viewer`
//! processes follow both cameras through Zenoh, one started before the cameras (it
//! gets the scans live), one after they finished (it gets them by query); each must
//! draw both models, each in its camera's colour. A gateway in this process checks
//! the merged model scan by scan against each daemon's own (TCP) model: same poses,
//! so the cameras overlay as the truth says. A Zenoh peer written with the Python
//! `eclipse-zenoh` package reads the same scans. And a camera guarded by Zenoh's
//! user/password authentication refuses a wrong credential.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::Duration;

use texel::model::Model;
use texel_client::zenoh_gateway::{Gateway, GatewayOptions, global_id};
use texel_client::{Client, Replica};
use texel_e2e::{Texeld, repo_root, run_python, workspace_binary};
use texel_viewer::composite::scan_colour;

const SITE: &str = "e2e";

/// A free loopback port (bound and released; the camera binds it right after).
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn endpoint(port: u16) -> String {
    format!("tcp/127.0.0.1:{port}")
}

/// A simulated camera publishing on Zenoh at `port`; `extra` is appended to `[zenoh]`.
fn camera_session(
    dir: &Path,
    camera: &str,
    seed: u64,
    frames: usize,
    port: u16,
    extra: &str,
) -> PathBuf {
    let path = dir.join(format!("{camera}.toml"));
    let scene = repo_root().join("configs/scenes/lab.toml");
    std::fs::write(
        &path,
        format!(
            "[session]\nname = \"{camera}\"\nexit_when_sources_end = false\n\
             [[source.sim]]\nscene = {scene:?}\nseed = {seed}\nframes = {frames}\n\
             lidar_size = [64, 48]\neo_size = [160, 120]\nspeed = 0.5\n\
             late = \"wait\"\ntruth = true\nrender_threads = 1\n\
             [pipeline]\noverload = \"backpressure\"\n\
             [serve]\nbind = \"127.0.0.1:0\"\ntexture = \"png\"\nweb = false\n\
             [status]\ninterval_ms = 500\n\
             [model.retirement]\nenabled = false\n\
             [zenoh]\nenabled = true\nsite = \"{SITE}\"\ncamera = \"{camera}\"\n\
             listen = [\"{}\"]\n{extra}\n",
            endpoint(port)
        ),
    )
    .unwrap();
    path
}

/// `texel-viewer render --zenoh` of every camera, waiting for `scans`, from scan
/// `acquisition`'s pose in scan-colour mode.
fn spawn_viewer(
    out: &Path,
    endpoints: &[String],
    scans: usize,
    acquisition: u64,
    extra: &[&str],
) -> Child {
    let mut cmd = Command::new(workspace_binary("texel-viewer"));
    cmd.args(["render", "--zenoh", "--site", SITE, "--camera", "*"]);
    for e in endpoints {
        cmd.args(["--zenoh-connect", e]);
    }
    cmd.args(["--wait-scans", &scans.to_string(), "--timeout-s", "120"])
        .args(["--acquisition", &acquisition.to_string()])
        .args([
            "--width",
            "320",
            "--height",
            "240",
            "--mode",
            "scan-colour",
            "--out",
        ])
        .arg(out)
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("texel-viewer (built by cargo test --workspace)")
}

/// Pixels of `img` within 3/255 of `colour` (linear [0, 1] RGB as the mode writes it).
fn pixels_of(img: &image::RgbaImage, colour: [f32; 3]) -> usize {
    let want = colour.map(|c| (c * 255.0).round() as i32);
    img.pixels()
        .filter(|p| (0..3).all(|c| (i32::from(p[c]) - want[c]).abs() <= 3))
        .count()
}

/// Both cameras' colours cover a fair share of a viewer's image.
fn assert_both_cameras_drawn(name: &str, output: &Output, out: &Path, scans: usize) {
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{name}: {stderr}");
    assert!(
        stderr.contains(&format!(": {scans} scans")),
        "{name}: {stderr}"
    );
    let img = image::open(out).unwrap().to_rgba8();
    let total = (img.width() * img.height()) as usize;
    for camera in [1usize, 2] {
        let n = pixels_of(&img, scan_colour((camera as u32) << 24));
        println!(
            "{name}: camera {camera}'s colour on {:.1} % of the pixels",
            100.0 * n as f64 / total as f64
        );
        assert!(
            n * 50 > total,
            "{name}: camera {camera} hardly drawn ({n} of {total} pixels)"
        );
    }
}

/// A daemon's model as a TCP viewer gets it.
fn tcp_model(daemon: &mut Texeld, scans: usize) -> Model {
    let addr = daemon.wait_for("serving viewers on ");
    texel_viewer::live::fetch::fetch_model(&addr, "", scans, Duration::from_secs(180)).unwrap()
}

#[test]
fn two_cameras_two_viewers_and_a_python_peer_share_the_models() {
    let dir = tempfile::tempdir().unwrap();
    let (port_a, port_b) = (free_port(), free_port());
    let endpoints = [endpoint(port_a), endpoint(port_b)];
    let (frames_a, frames_b) = (5usize, 4usize);
    let total = frames_a + frames_b;

    let mut cam_a = Texeld::start(&camera_session(
        dir.path(),
        "cam-a",
        5,
        frames_a,
        port_a,
        "",
    ));
    let connect_a = format!("connect = [\"{}\"]", endpoint(port_a));
    let mut cam_b = Texeld::start(&camera_session(
        dir.path(),
        "cam-b",
        6,
        frames_b,
        port_b,
        &connect_a,
    ));
    let published = cam_a.wait_for("zenoh: publishing ");
    assert!(
        published.starts_with(&format!(
            "texel/{SITE}/cam-a (peer, world frame \"sim:lab\")"
        )),
        "{published}"
    );
    cam_b.wait_for("zenoh: publishing ");

    // The early viewer: joins while the cameras are still at their first frames (at
    // half speed), so most scans reach it live.
    let early_png = dir.path().join("early.png");
    let early = spawn_viewer(&early_png, &endpoints, total, 1 << 24, &[]);
    let model_a = tcp_model(&mut cam_a, frames_a);
    let model_b = tcp_model(&mut cam_b, frames_b);

    let early = early.wait_with_output().unwrap();
    assert_both_cameras_drawn("early viewer", &early, &early_png, total);

    // The late viewer: every scan was published before it started.
    let late_png = dir.path().join("late.png");
    let late = spawn_viewer(&late_png, &endpoints, total, 2 << 24, &[])
        .wait_with_output()
        .unwrap();
    assert_both_cameras_drawn("late viewer", &late, &late_png, total);

    // The merged model, scan by scan, against each daemon's own.
    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(async {
        let mut config = zenoh::Config::default();
        config.insert_json5("listen/endpoints", "[]").unwrap();
        config
            .insert_json5(
                "connect/endpoints",
                &serde_json::to_string(&endpoints).unwrap(),
            )
            .unwrap();
        config
            .insert_json5("scouting/multicast/enabled", "false")
            .unwrap();
        let gateway = Gateway::start(GatewayOptions::new(SITE, "*", config))
            .await
            .unwrap();
        let mut client = Client::connect(gateway.addr, "", "test").await.unwrap();
        let mut replica = Replica::new();
        tokio::time::timeout(Duration::from_secs(60), async {
            while replica.model.resident().count() < total {
                let m = client.next_message().await.unwrap().unwrap();
                replica.apply(m).unwrap();
            }
        })
        .await
        .expect("the merged model within 60 s");
        let cameras = gateway.cameras();
        assert_eq!(cameras.len(), 2, "{cameras:?}");
        for view in &cameras {
            assert_eq!(view.world_frame.as_deref(), Some("sim:lab"));
            let own = if view.prefix.ends_with("cam-a") {
                &model_a
            } else {
                &model_b
            };
            assert_eq!(view.scans, own.len(), "{view:?}");
            for scan in own.scans() {
                let merged = replica
                    .model
                    .get(global_id(view.number, scan.id).unwrap())
                    .unwrap();
                assert_eq!(
                    merged.world_from_scan, scan.world_from_scan,
                    "{} scan {}",
                    view.prefix, scan.id
                );
                let (a, b) = (merged.scan.as_ref().unwrap(), scan.scan.as_ref().unwrap());
                assert_eq!(a.timestamp_ns, b.timestamp_ns);
                assert_eq!(a.vertices.len(), b.vertices.len());
            }
        }
    });

    // A Zenoh peer that is not ours reads the same scans.
    let python = run_python(
        "zenoh_subscriber.py",
        &[
            "--connect".as_ref(),
            endpoints[0].as_ref(),
            "--site".as_ref(),
            SITE.as_ref(),
            "--listen-s".as_ref(),
            "1.2".as_ref(),
        ],
    );
    assert!(
        python.status.success(),
        "{}",
        String::from_utf8_lossy(&python.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&python.stdout).unwrap();
    for (camera, own) in [("cam-a", &model_a), ("cam-b", &model_b)] {
        let got = &report["cameras"][format!("texel/{SITE}/{camera}")];
        let mut scans: Vec<(u64, u64, u64)> = got["scans"]
            .as_array()
            .unwrap_or_else(|| panic!("{camera} missing from {report}"))
            .iter()
            .map(|s| {
                (
                    s["id"].as_u64().unwrap(),
                    s["timestamp_ns"].as_u64().unwrap(),
                    s["vertex_count"].as_u64().unwrap(),
                )
            })
            .collect();
        scans.sort_unstable();
        let want: Vec<(u64, u64, u64)> = own
            .scans()
            .iter()
            .map(|s| {
                let scan = s.scan.as_ref().unwrap();
                (s.id, scan.timestamp_ns, scan.vertices.len() as u64)
            })
            .collect();
        assert_eq!(scans, want, "{camera}");
    }
    let live = report["live_keys"].to_string();
    assert!(live.contains("/status"), "statuses arrive live: {live}");
}

#[test]
fn a_guarded_camera_refuses_a_wrong_credential() {
    let dir = tempfile::tempdir().unwrap();
    let users = dir.path().join("users.txt");
    std::fs::write(&users, "viewer:right-password\n").unwrap();
    let right = dir.path().join("right.txt");
    std::fs::write(&right, "right-password\n").unwrap();
    let wrong = dir.path().join("wrong.txt");
    std::fs::write(&wrong, "wrong-password\n").unwrap();
    let acl = repo_root().join("configs/zenoh/access-control.json5");
    let port = free_port();
    let guard = format!("access_control = {acl:?}\n[zenoh.auth]\ndictionary_file = {users:?}\n");
    let mut cam = Texeld::start(&camera_session(dir.path(), "guarded", 5, 3, port, &guard));
    cam.wait_for("zenoh: publishing ");
    tcp_model(&mut cam, 3);
    let endpoints = [endpoint(port)];
    let png = dir.path().join("x.png");
    let view = |file: &Path| {
        let mut child = spawn_viewer(
            &png,
            &endpoints,
            3,
            1 << 24,
            &[
                "--zenoh-user",
                "viewer",
                "--zenoh-password-file",
                file.to_str().unwrap(),
            ],
        );
        // The refused viewer would wait its whole timeout: give it 15 s.
        let deadline = std::time::Instant::now() + Duration::from_secs(15);
        while std::time::Instant::now() < deadline {
            if child.try_wait().unwrap().is_some() {
                return child.wait_with_output().unwrap();
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let _ = child.kill();
        child.wait_with_output().unwrap()
    };
    let refused = view(&wrong);
    assert!(!refused.status.success(), "a wrong password got the model");
    assert!(!png.exists(), "a wrong password drew an image");
    let admitted = view(&right);
    let stderr = String::from_utf8_lossy(&admitted.stderr);
    assert!(admitted.status.success(), "the right password: {stderr}");
    assert!(stderr.contains(": 3 scans"), "{stderr}");
}
