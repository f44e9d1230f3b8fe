//! Frames travel by reference: ingest hands the recorder, the live tap (Foxglove) and
//! the pair it forms the same range and EO frames (one allocation each, no copy), and fusion shares that EO
//! frame as the scan's texture whether or not the recorder has let go. The encode stage writes a
//! scan's frame from the scan itself, byte for byte what the owned `WireScan` path
//! writes, for every texture format.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::sync::Arc;

use bytes::Bytes;
use texel::sync::SharedFrameSync;
use texel::wire::{Message, TextureFormat, WireScan, check_sendable};
use texel::{FuseConfig, Pose, Sensor, fuse};
use texel_daemon::config::OverloadPolicy;
use texel_daemon::pipeline::encode::encode_scan;
use texel_daemon::pipeline::ingest::Ingest;
use texel_daemon::record::RecordItem;
use texel_daemon::source::{SourceEvent, Tagged};
use texel_daemon::status::Metrics;
use texel_e2e::captures;
use tokio::sync::mpsc;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_recorder_and_the_pair_share_one_frame() {
    let model = Arc::new(captures::sensor());
    let (range, eo) = captures::frame(&model, 3, 1_000);
    let (range, eo) = (Arc::new(range), Arc::new(eo));
    let (events_tx, events) = mpsc::channel(8);
    let (record_tx, mut record_rx) = mpsc::channel(8);
    let (pairs, mut pairs_rx) = mpsc::channel(8);
    let (tap, mut tapped) = texel_daemon::pipeline::tap::tap();
    let ingest = Ingest {
        events,
        record: Some(record_tx),
        pairs,
        sync: SharedFrameSync::new(0, 4),
        policy: OverloadPolicy::Backpressure,
        sensor: Some(Arc::clone(&model)),
        metrics: Metrics::new(),
        hub: texel_daemon::hub::Hub::new(8),
        tap: Some(tap),
    };
    let task = tokio::spawn(ingest.run());
    for event in [
        SourceEvent::Range(Arc::clone(&range)),
        SourceEvent::Eo(Arc::clone(&eo)),
    ] {
        events_tx.send(Tagged { source: 0, event }).await.unwrap();
    }
    drop(events_tx);
    let job = pairs_rx.recv().await.unwrap();
    task.await.unwrap();

    let mut recorded = Vec::new();
    while let Some(item) = record_rx.recv().await {
        recorded.push(item);
    }
    let [
        RecordItem::Sensor(_),
        RecordItem::Range(recorded_range),
        RecordItem::Eo(recorded_eo),
    ] = recorded.as_slice()
    else {
        panic!("recorded {recorded:?}");
    };
    assert!(Arc::ptr_eq(recorded_range, &range));
    assert!(Arc::ptr_eq(recorded_eo, &eo));
    assert!(Arc::ptr_eq(&job.pair.range, &range));
    assert!(Arc::ptr_eq(&job.pair.eo, &eo));
    // The live tap got the same records, sharing the same frames.
    let tapped = tokio::task::spawn_blocking(move || {
        std::iter::from_fn(|| tapped.blocking_recv()).collect::<Vec<_>>()
    })
    .await
    .unwrap();
    let [
        RecordItem::Sensor(_),
        RecordItem::Range(tapped_range),
        RecordItem::Eo(tapped_eo),
    ] = tapped.as_slice()
    else {
        panic!("tapped {tapped:?}");
    };
    assert!(Arc::ptr_eq(tapped_range, &range));
    assert!(Arc::ptr_eq(tapped_eo, &eo));
    drop(tapped);

    // The recorder has not let go yet: fusion still shares the very frame, pixels and
    // all, as the scan's texture (no copy whoever else holds it).
    let scan = fuse(
        &job.pair.range,
        Arc::clone(&job.pair.eo),
        &Sensor::new((*model).clone()),
        &FuseConfig::default(),
    )
    .unwrap();
    assert!(Arc::ptr_eq(&scan.texture, recorded_eo));
    assert!(Arc::ptr_eq(&scan.texture, &eo));
    drop(recorded);
    assert_eq!(
        Arc::strong_count(&eo),
        3,
        "the source, the pair and the scan"
    );
}

#[test]
fn a_scan_frame_is_written_from_the_scan_as_the_owned_path_writes_it() {
    let model = captures::sensor();
    let (range, eo) = captures::frame(&model, 5, 2_000);
    let scan = fuse(&range, eo, &Sensor::new(model), &FuseConfig::default()).unwrap();
    check_sendable(&scan).unwrap();
    let world = captures::pose(5);
    for format in [TextureFormat::Rgb8, TextureFormat::Png, TextureFormat::Jpeg] {
        let frame = encode_scan(11, &scan, world, format, 90).unwrap();
        let texture = texel_daemon::texture::encode(&scan.texture, format, 90).unwrap();
        let owned = WireScan::with_texture(11, &scan, world, texture).unwrap();
        let expected = Message::ScanAdded(Box::new(owned)).encode().unwrap();
        assert_eq!(frame, Bytes::from(expected), "{format:?}");
    }
    // A pose the decoder would refuse is refused here too.
    let mut nan = Pose::identity();
    nan.translation.vector.z = f64::NAN;
    assert!(encode_scan(11, &scan, nan, TextureFormat::Rgb8, 90).is_err());
}
