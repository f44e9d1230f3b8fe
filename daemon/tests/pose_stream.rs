//! The recorded pose stream of a session with loop closures: a revision is recorded
//! for a keyframe only, every other frame's `/texel/anchor` derives its pose from its
//! keyframe's, and the poses the recording gives back are the ones a client holds.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
// The simulated sources are the `sim` feature (on by default).
#![cfg(feature = "sim")]

use std::collections::HashMap;
use std::path::Path;
use std::process::Command;
use std::time::Duration;

use texel::capture::{CaptureEvent, CaptureReader, PoseTopic, RegisteredPoses};
use texel::pose::pose_difference;
use texel::wire::TextureFormat;
use texel_client::{Client, Replica};
use texel_daemon::config::{
    LatePolicy, OverloadPolicy, RegistrationMode, SessionConfig, SimConfig,
};
use texel_daemon::pipeline::Session;
use texel_e2e::repo_root;
use tokio_util::sync::CancellationToken;

/// The whole walk: it comes back to where it started, so loop closure revises
/// keyframes and, through them, the frames hanging from them.
const FRAMES: usize = 200;

fn session(record: &Path) -> SessionConfig {
    let mut c = SessionConfig::default();
    c.source.sim = vec![SimConfig {
        scene: repo_root().join("configs/scenes/lab-walk.toml"),
        seed: 5,
        frames: Some(FRAMES),
        lidar_size: Some([48, 48]),
        eo_size: Some([160, 120]),
        fast: true,
        late: LatePolicy::Wait,
        render_threads: 2,
        ..SimConfig::default()
    }];
    c.session.exit_when_sources_end = true;
    c.pipeline.registration = RegistrationMode::Register;
    c.pipeline.overload = OverloadPolicy::Backpressure;
    c.serve.bind = "127.0.0.1:0".parse().unwrap();
    c.serve.texture = TextureFormat::Jpeg;
    c.record.path = Some(record.to_path_buf());
    c.status.log = false;
    // Every scan served, so the client holds every pose to compare.
    c.model.retirement.enabled = false;
    c.validate("test").unwrap();
    c
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn revisions_are_recorded_for_keyframes_and_the_rest_follow_their_anchors() {
    let dir = tempfile::tempdir().unwrap();
    let recording = dir.path().join("walk.mcap");
    let session = Session::start(session(&recording), CancellationToken::new())
        .await
        .unwrap();
    let mut client = Client::connect(session.local_addr.unwrap(), "", "test")
        .await
        .unwrap();
    let mut replica = Replica::new();
    tokio::time::timeout(Duration::from_secs(300), async {
        while let Some(m) = client.next_message().await.unwrap() {
            replica.apply(m).unwrap();
        }
    })
    .await
    .expect("the stream stalled");
    session.wait().await.unwrap();

    // The recording, as a reader sees it.
    let mut registered = RegisteredPoses::default();
    let mut pose_messages: HashMap<u64, usize> = HashMap::new();
    let mut anchors: HashMap<u64, u64> = HashMap::new();
    for e in CaptureReader::open(&recording).unwrap() {
        let event = e.unwrap();
        match &event {
            CaptureEvent::Pose {
                topic: PoseTopic::Texel,
                timestamp_ns,
                ..
            } => *pose_messages.entry(*timestamp_ns).or_default() += 1,
            CaptureEvent::Anchor(anchor) => {
                anchors.insert(anchor.timestamp_ns, anchor.keyframe_timestamp_ns);
            }
            _ => {}
        }
        registered.take_event(&event);
    }
    assert_eq!(registered.len(), replica.model.len());
    let is_keyframe = |t: u64| anchors.get(&t) == Some(&t);

    let (mut keyframes, mut hanging_revised, mut model_revisions) = (0, 0, 0);
    for s in replica.model.scans() {
        let t = s.listing.timestamp_ns;
        model_revisions += s.revisions;
        // Every registered frame says how it hangs.
        assert!(anchors.contains_key(&t), "frame at {t} ns has no anchor");
        let recorded = pose_messages[&t];
        if is_keyframe(t) {
            keyframes += 1;
        } else {
            // A hanging frame's pose is recorded once, when it is placed; its
            // revisions follow from its keyframe's.
            assert_eq!(recorded, 1, "hanging frame at {t} ns");
            hanging_revised += usize::from(s.revisions > 0);
        }
        // The pose a reader derives is the one the client holds, within the
        // revision thresholds (2 mm and 0.05 deg for the frame's own pose and for its
        // keyframe's, plus that angle over the lever between them).
        let (angle, dist) = pose_difference(&registered.get(t).unwrap(), &s.world_from_scan);
        assert!(
            angle < 0.1f64.to_radians() && dist < 0.006,
            "frame at {t} ns: {:.3} deg, {:.2} mm from the client's",
            angle.to_degrees(),
            dist * 1e3
        );
    }
    let messages: usize = pose_messages.values().sum();
    eprintln!(
        "{} frames, {keyframes} keyframes; the model made {model_revisions} revisions, \
         {hanging_revised} frames hanging from a keyframe were revised; the recording holds \
         {messages} /texel/pose and {} /texel/anchor messages",
        replica.model.len(),
        anchors.len()
    );
    // The walk closes its loop: frames hanging from keyframes were revised, and
    // the recording holds fewer poses than the model made revisions.
    assert!(hanging_revised > 0, "no hanging frame was revised");
    assert!(messages < replica.model.len() + model_revisions as usize);

    // `texeld register` replaces the registration as a whole: one pose per frame,
    // no anchor left to compose with a pose it no longer belongs to.
    let again = dir.path().join("again.mcap");
    let out = Command::new(env!("CARGO_BIN_EXE_texeld"))
        .args([
            "register".as_ref(),
            recording.as_os_str(),
            "--out".as_ref(),
            again.as_os_str(),
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (mut poses, mut anchors) = (0, 0);
    for e in CaptureReader::open(&again).unwrap() {
        match e.unwrap() {
            CaptureEvent::Pose {
                topic: PoseTopic::Texel,
                ..
            } => poses += 1,
            CaptureEvent::Anchor(_) => anchors += 1,
            _ => {}
        }
    }
    assert_eq!(anchors, 0);
    assert!(poses > 0 && poses <= FRAMES, "{poses} poses");
}
