//! The live session in Foxglove, checked by a client that is not ours: a simulated
//! session with `[foxglove]` on port 0, and `scripts/python/foxglove_client.py`
//! (the published Foxglove WebSocket protocol over the `websockets` package, the
//! messages decoded by `foxglove_schemas_protobuf`, each scan's glTF loaded by
//! trimesh) subscribed to `/texel/scan`, `/eo/calibration`, `/texel/pose` and
//! `/texel/status` (and to `/lidar/range` and `/eo/image`). Against ground truth: each scan model's vertex and triangle
//! counts, texture size and bounds are the served scan's (the hub's frame), its pose
//! is `world_from_scan`, the schemas are the recording's, the calibration is the
//! sensor's; a revision, a new scan and a withdrawal made on the hub reach the client
//! live. And a bad `[foxglove]` section is refused, naming the key.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
#![cfg(all(feature = "sim", feature = "foxglove-live"))]

use std::collections::BTreeMap;
use std::io::BufRead;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use serde_json::Value;
use texel::Pose;
use texel::model::{ScanId, ScanListing};
use texel::pose::{pose_from_parts, pose_to_parts};
use texel::wire::{Limits, Message, WireScan, decode_frame};
use texel_daemon::config::{LatePolicy, OverloadPolicy, SessionConfig, SimConfig};
use texel_daemon::pipeline::Session;
use texel_daemon::source::sim::build_simulator;
use texel_e2e::{python, repo_root};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

const FRAMES: usize = 8;
/// The id of the scan the test adds to the hub itself (after the simulator's).
const ADDED: ScanId = 999;

fn sim_config() -> SimConfig {
    SimConfig {
        scene: repo_root().join("configs/scenes/lab.toml"),
        seed: 3,
        frames: Some(FRAMES),
        eo_size: Some([160, 120]),
        // At the trajectory's 10 Hz: the client joins while frames still arrive.
        fast: false,
        late: LatePolicy::Wait,
        render_threads: 2,
        ..SimConfig::default()
    }
}

fn session(record: &Path) -> SessionConfig {
    let mut c = SessionConfig::default();
    c.source.sim = vec![sim_config()];
    c.pipeline.overload = OverloadPolicy::Backpressure;
    c.serve.bind = "127.0.0.1:0".parse().unwrap();
    c.record.path = Some(record.to_path_buf());
    c.status.log = false;
    c.status.interval_ms = 200;
    c.foxglove.enabled = true;
    c.foxglove.bind = "127.0.0.1:0".parse().unwrap();
    c.validate("test").unwrap();
    c
}

/// The client's JSON lines, as they come.
struct Client {
    child: Child,
    lines: mpsc::UnboundedReceiver<Value>,
    seen: Vec<Value>,
}

impl Client {
    fn start(url: &str, until_deleted: ScanId) -> Self {
        let script = repo_root().join("scripts/python/foxglove_client.py");
        let mut child = Command::new(python())
            .arg(&script)
            .arg(url)
            .args([
                "--subscribe",
                "/texel/scan",
                "/eo/calibration",
                "/texel/pose",
                "/texel/status",
                // Raw frames only arrive while the simulator runs: checked when seen.
                "/lidar/range",
                "/eo/image",
            ])
            .args(["--until-deleted", &until_deleted.to_string()])
            .args(["--timeout", "120"])
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot run {}: {e}", script.display()));
        let stdout = child.stdout.take().unwrap();
        let (tx, lines) = mpsc::unbounded_channel();
        std::thread::spawn(move || {
            for line in std::io::BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                let value = serde_json::from_str(&line)
                    .unwrap_or_else(|e| panic!("not JSON from the client: {line}: {e}"));
                if tx.send(value).is_err() {
                    break;
                }
            }
        });
        Self {
            child,
            lines,
            seen: Vec::new(),
        }
    }

    /// Waits for the first line (from now) that `want` accepts.
    async fn until(&mut self, what: &str, want: impl Fn(&Value) -> bool) -> Value {
        let wait = async {
            while let Some(v) = self.lines.recv().await {
                self.seen.push(v.clone());
                if want(&v) {
                    return Some(v);
                }
            }
            None
        };
        match tokio::time::timeout(Duration::from_secs(60), wait).await {
            Ok(Some(v)) => v,
            _ => {
                let _ = self.child.kill();
                let out = self.child.wait_with_output_now();
                let seen: Vec<String> = self
                    .seen
                    .iter()
                    .map(|v| {
                        let mut v = v.to_string();
                        v.truncate(300);
                        v
                    })
                    .collect();
                panic!(
                    "the client never showed {what}; it showed:\n{}\nits stderr:\n{out}",
                    seen.join("\n")
                );
            }
        }
    }
}

trait StderrNow {
    fn wait_with_output_now(&mut self) -> String;
}

impl StderrNow for Child {
    fn wait_with_output_now(&mut self) -> String {
        let _ = self.wait();
        let mut s = String::new();
        if let Some(mut e) = self.stderr.take() {
            let _ = std::io::Read::read_to_string(&mut e, &mut s);
        }
        s
    }
}

/// The entities of a `/texel/scan` message line.
fn entities(v: &Value) -> Vec<&Value> {
    if v["topic"] != "/texel/scan" {
        return Vec::new();
    }
    v["entities"]
        .as_array()
        .map(|a| a.iter().collect())
        .unwrap_or_default()
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

/// A model primitive's pose as (translation, quaternion xyzw).
fn primitive_pose(model: &Value) -> ([f64; 3], [f64; 4]) {
    let t = floats(&model["pose"]["position"]);
    let q = floats(&model["pose"]["orientation"]);
    ([t[0], t[1], t[2]], [q[0], q[1], q[2], q[3]])
}

fn assert_pose(model: &Value, expected: &Pose, what: &str) {
    let (t, q) = primitive_pose(model);
    let (et, eq) = pose_to_parts(expected);
    for (a, b) in t.iter().chain(&q).zip(et.iter().chain(&eq)) {
        assert!(
            (a - b).abs() < 1e-12,
            "{what}: pose {t:?} {q:?}, expected {et:?} {eq:?}"
        );
    }
}

/// The served scan `id` as the hub holds it.
fn served_scan(session: &Session, id: ScanId) -> WireScan {
    let frame = session.hub.fetch_scan(id).unwrap();
    match decode_frame(&frame, &Limits::FROM_SERVER).unwrap() {
        Some((Message::ScanAdded(wire), _)) => *wire,
        other => panic!("scan {id}: {other:?}"),
    }
}

/// What a model of `scan` must show: vertices, usable triangles, texture size, bounds.
fn check_model(model: &Value, scan: &WireScan, what: &str) {
    assert_eq!(model["media_type"], "model/gltf-binary", "{what}");
    assert_eq!(model["meshes"], 1, "{what}");
    assert_eq!(model["vertices"], scan.vertices.len(), "{what}: vertices");
    let usable = scan.triangle_flags.iter().filter(|f| f.is_usable()).count();
    assert_eq!(model["faces"], usable, "{what}: triangles");
    assert_eq!(
        model["textures"],
        serde_json::json!([[scan.texture.width, scan.texture.height]]),
        "{what}: texture"
    );
    assert_eq!(floats(&model["scale"]), vec![1.0; 3], "{what}: scale");
    // Shown as Foxglove shows it: in the scan's own frame.
    let (lo, hi) = texel::scan::bounds_of(&scan.vertices).unwrap();
    for (got, want) in [(floats(&model["min"]), lo), (floats(&model["max"]), hi)] {
        for (g, w) in got.iter().zip(want) {
            assert!(
                (g - f64::from(w)).abs() < 1e-5,
                "{what}: bounds {got:?}, expected {want:?}"
            );
        }
    }
}

/// Topic -> (schema name, message encoding) of a capture.
fn recorded_channels(path: &Path) -> BTreeMap<String, (String, String)> {
    let bytes = std::fs::read(path).unwrap();
    let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
    summary
        .channels
        .values()
        .map(|c| {
            let schema = c
                .schema
                .as_ref()
                .map(|s| s.name.clone())
                .unwrap_or_default();
            (c.topic.clone(), (schema, c.message_encoding.clone()))
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_foxglove_client_sees_the_live_model_as_the_recording_has_it() {
    let dir = tempfile::tempdir().unwrap();
    let record = dir.path().join("live.mcap");
    let sim = build_simulator(&sim_config().setup()).unwrap();
    let stop = CancellationToken::new();
    let session = Session::start(session(&record), stop.clone())
        .await
        .unwrap();
    let addr = session.foxglove_addr.expect("the Foxglove server is on");
    assert_ne!(addr.port(), 0);
    let mut client = Client::start(&format!("ws://{addr}"), ADDED);

    let connected = client
        .until("connected", |v| v["event"] == "connected")
        .await;
    eprintln!("client: {connected}");
    assert_eq!(connected["subprotocol"], "foxglove.sdk.v1");

    // Every simulated scan is in the model, and the client has each served one.
    tokio::time::timeout(Duration::from_secs(90), session.sources_done.cancelled())
        .await
        .expect("the simulator never ended");
    tokio::time::timeout(Duration::from_secs(60), async {
        while session.hub.scan_count() < FRAMES {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await
    .expect("the model never held every frame");
    let snapshot = session.hub.subscribe().unwrap();
    session.hub.unsubscribe(snapshot.client_id);
    let served: BTreeMap<ScanId, (ScanListing, Pose)> = snapshot
        .snapshot
        .iter()
        .filter_map(|f| match decode_frame(f, &Limits::FROM_SERVER).unwrap() {
            Some((
                Message::ScanListed {
                    id,
                    listing,
                    world_from_scan,
                },
                _,
            )) => Some((id, (listing, world_from_scan))),
            _ => None,
        })
        .collect();
    assert!(!served.is_empty());
    let mut last: BTreeMap<String, Value> = BTreeMap::new();
    let have_all = |last: &BTreeMap<String, Value>| {
        served.iter().all(|(id, (_, pose))| {
            last.get(&id.to_string())
                .is_some_and(|e| primitive_pose(&e["models"][0]) == pose_to_parts(pose))
        })
    };
    while !have_all(&last) {
        let v = client
            .until("every served scan", |v| !entities(v).is_empty())
            .await;
        for e in entities(&v) {
            last.insert(e["id"].as_str().unwrap().to_string(), e.clone());
        }
    }
    let sizes: Vec<u64> = last
        .values()
        .filter_map(|e| e["models"][0]["glb_bytes"].as_u64())
        .collect();
    eprintln!(
        "{} scans registered, {} served, {} /texel/scan entities received; glTF {}..{} bytes",
        session.hub.scan_count(),
        served.len(),
        client.seen.iter().map(|v| entities(v).len()).sum::<usize>(),
        sizes.iter().min().unwrap_or(&0),
        sizes.iter().max().unwrap_or(&0),
    );
    for (id, (listing, pose)) in &served {
        let e = &last[&id.to_string()];
        let what = format!("scan {id}");
        assert_eq!(e["frame_id"], "world", "{what}");
        assert_eq!(e["timestamp_ns"], listing.timestamp_ns, "{what}");
        assert_pose(&e["models"][0], pose, &what);
        check_model(&e["models"][0], &served_scan(&session, *id), &what);
    }

    // Live: a revision re-sends the entity at its new pose with the same model bytes.
    let (&revised, _) = served.iter().next().unwrap();
    let moved = pose_from_parts(
        [1.5, -2.25, 0.75],
        [0.0, 0.0, 0.258_819_045_102_520_76, 0.965_925_826_289_068_3],
    )
    .unwrap();
    session.hub.revise_pose(revised, moved).unwrap();
    let key = revised.to_string();
    let v = client
        .until("the revision", |v| {
            entities(v).iter().any(|e| {
                e["id"] == key.as_str() && primitive_pose(&e["models"][0]) == pose_to_parts(&moved)
            })
        })
        .await;
    let e = entities(&v)
        .into_iter()
        .find(|e| e["id"] == key.as_str())
        .unwrap();
    assert_pose(&e["models"][0], &moved, "the revised scan");
    assert_eq!(
        e["models"][0]["glb_bytes"],
        last[&key]["models"][0]["glb_bytes"]
    );

    // Live: a scan added to the hub (a copy of the first at another pose) arrives,
    // then its withdrawal (the client ends there).
    let wire = served_scan(&session, revised);
    let (_, scan, _) = wire.clone().into_scan().unwrap();
    let placed = pose_from_parts([-3.0, 4.0, 0.5], [0.0, 0.0, 0.0, 1.0]).unwrap();
    let frame = texel_daemon::pipeline::encode::encode_scan(
        ADDED,
        &scan,
        placed,
        texel::wire::TextureFormat::Jpeg,
        90,
    )
    .unwrap();
    let listing = ScanListing::of_scan(&scan, frame.len() as u64, 0.0);
    session
        .hub
        .add_scan(ADDED, listing, placed, frame, false, None)
        .unwrap();
    let added = ADDED.to_string();
    let v = client
        .until("the added scan", |v| {
            entities(v).iter().any(|e| e["id"] == added.as_str())
        })
        .await;
    let e = entities(&v)
        .into_iter()
        .find(|e| e["id"] == added.as_str())
        .unwrap();
    assert_pose(&e["models"][0], &placed, "the added scan");
    check_model(&e["models"][0], &wire, "the added scan");
    session.hub.withdraw(ADDED).unwrap();
    let v = client
        .until("the withdrawal", |v| {
            v["deleted"]
                .as_array()
                .is_some_and(|d| d.iter().any(|d| d == added.as_str()))
        })
        .await;
    assert_eq!(v["deletion_types"], serde_json::json!([0]), "MATCHING_ID");
    client.until("the end", |v| v["event"] == "done").await;
    let status = client.child.wait().unwrap();
    assert!(status.success(), "{}", client.child.wait_with_output_now());

    stop.cancel();
    let summary = tokio::time::timeout(Duration::from_secs(30), session.wait())
        .await
        .expect("the session did not stop")
        .unwrap();
    assert!(summary.scans >= FRAMES);

    // The topics' schemas are the recording's.
    let recorded = recorded_channels(&record);
    let advertised: BTreeMap<String, (String, String)> = client
        .seen
        .iter()
        .filter(|v| v["event"] == "advertise")
        .flat_map(|v| v["channels"].as_array().unwrap().clone())
        .map(|c| {
            let s = |k: &str| c[k].as_str().unwrap_or_default().to_string();
            (s("topic"), (s("schemaName"), s("encoding")))
        })
        .collect();
    eprintln!("advertised: {advertised:?}");
    let mut compared = Vec::new();
    for (topic, schema) in &recorded {
        if let Some(live) = advertised.get(topic) {
            assert_eq!(live, schema, "{topic}");
            compared.push(topic.as_str());
        }
    }
    for topic in [
        "/lidar/calibration",
        "/eo/calibration",
        "/tf_static",
        "/texel/sensor",
        "/lidar/range",
        "/eo/image",
        "/truth/pose",
        "/texel/pose",
    ] {
        assert!(
            compared.contains(&topic),
            "{topic} not compared: {compared:?}"
        );
    }
    assert_eq!(
        advertised["/texel/scan"],
        ("foxglove.SceneUpdate".to_string(), "protobuf".to_string())
    );
    assert_eq!(
        advertised["/texel/status"],
        ("texel.Status".to_string(), "json".to_string())
    );

    // The calibration is the sensor's (latched: the client may have come late).
    let eo = &sim.sensor_model().eo;
    let calibration = client
        .seen
        .iter()
        .find(|v| v["topic"] == "/eo/calibration")
        .expect("no /eo/calibration");
    let (model, d) = eo.distortion_fields();
    assert_eq!(calibration["frame_id"], "eo");
    assert_eq!(
        (
            calibration["width"].as_u64(),
            calibration["height"].as_u64()
        ),
        (Some(u64::from(eo.width)), Some(u64::from(eo.height)))
    );
    assert_eq!(floats(&calibration["K"]), eo.k_row_major().to_vec());
    assert_eq!(floats(&calibration["D"]), d);
    assert_eq!(calibration["distortion_model"], model);

    // Every /texel/pose is one the recording holds (the latest latched for a late
    // joiner, then each new one and each revision).
    let mut recorded_poses = Vec::new();
    for e in texel::capture::CaptureReader::open(&record).unwrap() {
        if let texel::capture::CaptureEvent::Pose {
            topic: texel::capture::PoseTopic::Texel,
            timestamp_ns,
            world_from_eo,
        } = e.unwrap()
        {
            recorded_poses.push((timestamp_ns, pose_to_parts(&world_from_eo)));
        }
    }
    let poses: Vec<&Value> = client
        .seen
        .iter()
        .filter(|v| v["topic"] == "/texel/pose")
        .collect();
    assert!(!poses.is_empty(), "no /texel/pose");
    for p in &poses {
        assert_eq!(
            (p["parent"].as_str(), p["child"].as_str()),
            (Some("world"), Some("eo"))
        );
        let t = floats(&p["translation"]);
        let q = floats(&p["rotation"]);
        let timestamp = p["timestamp_ns"].as_u64().unwrap();
        // The recording's reader normalises the quaternion: equal to its rounding.
        let close = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(a, b)| (a - b).abs() < 1e-12);
        assert!(
            recorded_poses
                .iter()
                .any(|(rt, (tt, qq))| *rt == timestamp && close(tt, &t) && close(qq, &q)),
            "/texel/pose at {timestamp} is not in the recording: {p}"
        );
    }

    // Raw frames, as the recording has them (those sent while the client was there).
    let sensor = sim.sensor_model();
    let (mut ranges, mut images) = (0, 0);
    for v in &client.seen {
        let (camera, encoding, bpp) = match v["topic"].as_str() {
            Some("/lidar/range") => (&sensor.lidar, "32FC1", 4),
            Some("/eo/image") => (&sensor.eo, "rgb8", 3),
            _ => continue,
        };
        if bpp == 4 {
            ranges += 1;
        } else {
            images += 1;
        }
        assert_eq!(v["encoding"], encoding, "{v}");
        assert_eq!(
            (v["width"].as_u64(), v["height"].as_u64()),
            (
                Some(u64::from(camera.width)),
                Some(u64::from(camera.height))
            ),
            "{v}"
        );
        assert_eq!(
            v["step"].as_u64(),
            Some(u64::from(camera.width) * bpp),
            "{v}"
        );
        assert_eq!(
            v["bytes"].as_u64(),
            Some(u64::from(camera.width * camera.height) * bpp)
        );
    }

    // The status, with what the Foxglove server did.
    let status = client
        .seen
        .iter()
        .rev()
        .find(|v| v["topic"] == "/texel/status")
        .expect("no /texel/status");
    assert!(status["json"]["model"]["scans"].as_u64().unwrap() >= FRAMES as u64);
    assert!(status["json"]["foxglove"]["scan_models"].as_u64().unwrap() >= served.len() as u64);
    eprintln!(
        "{ranges} /lidar/range, {images} /eo/image, {} /texel/pose, {} /texel/status \
         messages; foxglove status {}",
        poses.len(),
        client
            .seen
            .iter()
            .filter(|v| v["topic"] == "/texel/status")
            .count(),
        status["json"]["foxglove"]
    );
}

#[test]
fn a_bad_foxglove_section_is_refused_naming_the_key() {
    let base = r#"
        [[source.sim]]
        scene = "configs/scenes/lab.toml"
    "#;
    let check = |extra: &str| {
        let text = format!("{base}\n{extra}");
        SessionConfig::from_toml_str(&text, "s.toml")
            .and_then(|c| c.validate("s.toml").map(|()| c))
            .map(|_| ())
            .map_err(|e| e.to_string())
    };
    // Off by default; loopback needs nothing more.
    check("").unwrap();
    check("[foxglove]\nenabled = true").unwrap();
    let remote = check("[foxglove]\nenabled = true\nbind = \"0.0.0.0:8765\"").unwrap_err();
    eprintln!("{remote}");
    assert!(
        remote.contains("foxglove.bind") && remote.contains("allow_remote"),
        "{remote}"
    );
    check("[foxglove]\nenabled = true\nbind = \"0.0.0.0:8765\"\nallow_remote = true").unwrap();
    let unknown = check("[foxglove]\nenabled = true\nprot = 8765").unwrap_err();
    eprintln!("{unknown}");
    assert!(
        unknown.contains("foxglove") && unknown.contains("unknown field"),
        "{unknown}"
    );
    let queue = check("[foxglove]\nenabled = true\nclient_queue = 0").unwrap_err();
    assert!(queue.contains("foxglove.client_queue"), "{queue}");

    // The command line: exit 2, the key on stderr, before anything starts.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("bad.toml");
    std::fs::write(
        &file,
        format!(
            "[[source.sim]]\nscene = {:?}\n[foxglove]\nenabled = true\nbind = \"0.0.0.0:0\"\n",
            repo_root().join("configs/scenes/lab.toml")
        ),
    )
    .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_texeld"))
        .args(["run", "--config"])
        .arg(&file)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("foxglove.bind"), "{stderr}");
}
