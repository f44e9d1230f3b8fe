//! The capture format end to end inside the project: every encoding round-trips,
//! truncated files yield exactly their complete messages and then an error saying
//! where the file ends, the writer flushes on time, and spec violations are named.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::cell::RefCell;
use std::io::{Cursor, Seek, SeekFrom, Write};
use std::rc::Rc;
use std::time::Duration;

use texel::capture::{
    CaptureError, CaptureEvent, CaptureReader, CaptureWriter, EoEncoding, ExposureRecord,
    PoseAnchor, PoseTopic, RangeEncoding, TexelItem, WriterOptions, open_texel_frames,
};
use texel::pose::pose_from_parts;
use texel::{Distortion, EoFrame, PinholeCamera, PlumbBob, RangeFrame, RangeNoise, SensorModel};

fn sensor() -> SensorModel {
    SensorModel {
        name: "unit".into(),
        lidar: PinholeCamera {
            width: 8,
            height: 6,
            fx: 10.0,
            fy: 10.0,
            cx: 3.5,
            cy: 2.5,
            skew: 0.0,
            distortion: Distortion::None,
        },
        eo: PinholeCamera {
            width: 16,
            height: 12,
            fx: 20.0,
            fy: 21.0,
            cx: 7.5,
            cy: 5.5,
            skew: 0.0,
            distortion: Distortion::PlumbBob(PlumbBob {
                k1: -0.1,
                k2: 0.01,
                p1: 0.0,
                p2: 0.001,
                k3: 0.0,
            }),
        },
        eo_from_lidar: pose_from_parts([0.02, 0.0, -0.01], [0.0, 0.01, 0.0, 1.0]).unwrap(),
        range_noise: RangeNoise {
            sigma_m: 0.005,
            sigma_per_m: 0.001,
        },
        range_bias_m: 0.0,
        min_range_m: 0.3,
        max_range_m: 25.0,
        // The response curve travels in `/texel/sensor`.
        eo_response: Some(texel::radiance::EoResponse::srgb()),
    }
}

fn range_frame(i: u32) -> RangeFrame {
    let mut f = RangeFrame::empty(8, 6, 1_000_000_000 + u64::from(i) * 33_000_000, i);
    for (k, r) in f.ranges_m.iter_mut().enumerate() {
        if !(k + i as usize).is_multiple_of(5) {
            *r = 0.5 + 0.01 * k as f32 + i as f32;
        }
    }
    f.intensity = Some((0..48).map(|k| (k * 100 + i) as f32).collect());
    f
}

fn eo_frame(i: u32, t: u64) -> EoFrame {
    EoFrame {
        width: 16,
        height: 12,
        rgb: (0..16 * 12 * 3)
            .map(|k| ((k as u32 * 7 + i * 11) % 256) as u8)
            .collect(),
        timestamp_ns: t,
        exposure: None,
    }
}

/// A shared in-memory sink, so a test can look at the bytes while the writer is open.
#[derive(Clone, Default)]
struct SharedSink(Rc<RefCell<Cursor<Vec<u8>>>>);

impl Write for SharedSink {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.borrow_mut().write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Seek for SharedSink {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        self.0.borrow_mut().seek(pos)
    }
}

impl SharedSink {
    fn len(&self) -> u64 {
        self.0.borrow().get_ref().len() as u64
    }
    fn bytes(&self) -> Vec<u8> {
        self.0.borrow().get_ref().clone()
    }
}

fn read_all(bytes: &[u8]) -> (Vec<CaptureEvent>, Option<CaptureError>) {
    let mut events = Vec::new();
    for item in CaptureReader::new(Cursor::new(bytes), Some(bytes.len() as u64), "mem".into()) {
        match item {
            Ok(e) => events.push(e),
            Err(e) if e.is_fatal() => return (events, Some(e)),
            Err(e) => panic!("unexpected spec error {e}"),
        }
    }
    (events, None)
}

#[test]
fn every_encoding_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("all.mcap");
    let model = sensor();
    let mut w = CaptureWriter::create(&path, WriterOptions::default()).unwrap();
    w.write_sensor(&model, 1).unwrap();
    let mut expected = Vec::new();
    let mut anchors = Vec::new();
    for (i, eo_enc) in EoEncoding::ALL.iter().enumerate() {
        let i = i as u32;
        let r = range_frame(i);
        let range_enc = if i.is_multiple_of(2) {
            RangeEncoding::F32Metres
        } else {
            RangeEncoding::U16Millimetres
        };
        w.write_range(&r, range_enc).unwrap();
        let mut e = eo_frame(i, r.timestamp_ns);
        // Every other frame says how it was exposed; the others (as captures before
        // `/eo/exposure` did) say nothing.
        if i % 2 == 1 {
            e.exposure = Some(texel::EoExposure {
                exposure_time_s: 1.0 / (60.0 * f64::from(i)),
                gain: 1.0 + f64::from(i),
            });
        } else if i == 2 {
            // An exposure for a frame that never comes is not given to the next one.
            w.write_exposure(&ExposureRecord {
                timestamp_ns: r.timestamp_ns - 1,
                exposure: texel::EoExposure {
                    exposure_time_s: 0.5,
                    gain: 1.0,
                },
            })
            .unwrap();
        }
        w.write_eo(&e, *eo_enc).unwrap();
        w.write_pose(
            PoseTopic::Truth,
            r.timestamp_ns,
            &pose_from_parts([i as f64, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0]).unwrap(),
        )
        .unwrap();
        // Each frame hangs from the first, logged later than the frame (as a
        // re-hung one is).
        let anchor = PoseAnchor {
            timestamp_ns: r.timestamp_ns,
            keyframe_timestamp_ns: range_frame(0).timestamp_ns,
            keyframe_from_eo: pose_from_parts([0.5, -0.25, i as f64], [0.1, 0.2, 0.3, 0.9])
                .unwrap(),
        };
        w.write_anchor(&anchor, r.timestamp_ns + 1).unwrap();
        anchors.push(anchor);
        expected.push((r, range_enc, e, *eo_enc));
    }
    // A compressed EO frame too.
    let r = range_frame(9);
    w.write_range(&r, RangeEncoding::F32Metres).unwrap();
    let mut e = eo_frame(9, r.timestamp_ns);
    e.exposure = Some(texel::EoExposure {
        exposure_time_s: 0.004,
        gain: 1.0,
    });
    w.write_exposure(&ExposureRecord {
        timestamp_ns: r.timestamp_ns,
        exposure: e.exposure.unwrap(),
    })
    .unwrap();
    let png = texel::capture::encode_compressed(&e.rgb, 16, 12, "png", 90).unwrap();
    w.write_eo_compressed(r.timestamp_ns, "png", png).unwrap();
    expected.push((r, RangeEncoding::F32Metres, e, EoEncoding::Rgb8));
    w.finish().unwrap();

    let mut pairs = Vec::new();
    let mut truth = 0;
    let mut read_anchors = Vec::new();
    let mut last_sensor = None;
    for item in open_texel_frames(&path).unwrap() {
        match item.unwrap() {
            TexelItem::Pair { pair, sensor } => {
                last_sensor = Some(sensor);
                pairs.push(pair);
            }
            TexelItem::Pose { topic, .. } => {
                assert_eq!(topic, PoseTopic::Truth);
                truth += 1;
            }
            TexelItem::Anchor(a) => read_anchors.push(a),
        }
    }
    assert_eq!(truth, 5);
    assert_eq!(read_anchors.len(), anchors.len());
    for (got, want) in read_anchors.iter().zip(&anchors) {
        assert_eq!(got.timestamp_ns, want.timestamp_ns);
        assert_eq!(got.keyframe_timestamp_ns, want.keyframe_timestamp_ns);
        assert_eq!(
            got.keyframe_from_eo.to_homogeneous(),
            want.keyframe_from_eo.to_homogeneous()
        );
    }
    assert_eq!(
        *last_sensor.unwrap(),
        model,
        "calibration, extrinsic and sensor JSON round-trip"
    );
    assert_eq!(pairs.len(), expected.len());
    for (pair, (r, range_enc, e, eo_enc)) in pairs.iter().zip(&expected) {
        assert_eq!(pair.range.timestamp_ns, r.timestamp_ns);
        assert_eq!(pair.eo.timestamp_ns, e.timestamp_ns);
        assert_eq!(pair.eo.exposure, e.exposure, "frame at {}", e.timestamp_ns);
        assert_eq!(pair.range.intensity, r.intensity);
        for (a, b) in pair.range.ranges_m.iter().zip(&r.ranges_m) {
            match range_enc {
                RangeEncoding::F32Metres => assert!(a == b || (a.is_nan() && b.is_nan())),
                RangeEncoding::U16Millimetres => {
                    assert!(
                        (a - b).abs() <= 0.0005 + 1e-6 || (a.is_nan() && b.is_nan()),
                        "{a} {b}"
                    )
                }
            }
        }
        match eo_enc {
            EoEncoding::Rgb8 | EoEncoding::Bgr8 | EoEncoding::Rgba8 => {
                assert_eq!(pair.eo.rgb, e.rgb)
            }
            EoEncoding::Mono8 | EoEncoding::Yuyv => {
                // Lossy by design; the decoded grey/colour must stay near the source.
                let mean = pair
                    .eo
                    .rgb
                    .iter()
                    .zip(&e.rgb)
                    .map(|(a, b)| f64::from(a.abs_diff(*b)))
                    .sum::<f64>()
                    / e.rgb.len() as f64;
                assert!(mean < 80.0, "{eo_enc:?}: mean abs difference {mean}");
            }
        }
    }
}

/// Writes `n` messages, closing a chunk after each, and returns the bytes and the
/// offset at which each message's chunk starts.
fn chunked_capture(n: usize, compression: Option<mcap::Compression>) -> (Vec<u8>, Vec<u64>) {
    let sink = SharedSink::default();
    let options = WriterOptions {
        compression,
        ..WriterOptions::default()
    };
    let mut w = CaptureWriter::new(sink.clone(), options, "mem".into()).unwrap();
    let model = sensor();
    w.write_calibration(texel::capture::CameraRole::Lidar, &model.lidar, 1)
        .unwrap();
    w.flush().unwrap();
    let mut starts = vec![];
    for i in 0..n {
        starts.push(sink.len());
        w.write_range(
            &RangeFrame {
                intensity: None,
                ..range_frame(i as u32)
            },
            RangeEncoding::F32Metres,
        )
        .unwrap();
        w.flush().unwrap();
    }
    w.finish().unwrap();
    (sink.bytes(), starts)
}

/// The end offset of the MCAP record starting at `offset` (opcode, u64 length, body).
fn record_end(bytes: &[u8], offset: u64) -> u64 {
    let o = offset as usize;
    assert_eq!(bytes[o], 0x06, "a chunk record starts here");
    let len = u64::from_le_bytes(bytes[o + 1..o + 9].try_into().unwrap());
    offset + 9 + len
}

#[test]
fn truncated_captures_yield_exactly_their_complete_messages() {
    for compression in [
        None,
        Some(mcap::Compression::Zstd),
        Some(mcap::Compression::Lz4),
    ] {
        let (bytes, starts) = chunked_capture(6, compression);
        // Message 0 is the calibration in the first chunk; range frame i is message i+1.
        let calibration_end = record_end(
            &bytes,
            8 + {
                // The header record comes first after the magic.
                let len = u64::from_le_bytes(bytes[9..17].try_into().unwrap());
                9 + len
            },
        );
        let mut ends = vec![calibration_end];
        ends.extend(starts.iter().map(|&s| record_end(&bytes, s)));
        let (all, err) = read_all(&bytes);
        assert!(err.is_none());
        assert_eq!(all.len(), 7);
        let seqs = |events: &[CaptureEvent]| -> Vec<u32> {
            events
                .iter()
                .map(|e| match e {
                    CaptureEvent::Range(f) => f.seq,
                    _ => u32::MAX,
                })
                .collect()
        };
        let all_seqs = seqs(&all);
        // A compressed chunk's last bytes can be a frame trailer (lz4's end mark and
        // checksum) after the last message byte: a cut there still leaves the message
        // whole and CRC-checked, so it may be yielded. Nowhere else may the count
        // differ from the number of chunks that end before the cut.
        const TRAILER: u64 = 16;
        let mut previous = 0;
        for cut in 0..=bytes.len() {
            let (events, err) = read_all(&bytes[..cut]);
            let cut64 = cut as u64;
            let complete = ends.iter().filter(|&&e| e <= cut64).count();
            let in_trailer = ends.iter().any(|&e| e > cut64 && e - cut64 <= TRAILER);
            let n = events.len();
            if in_trailer {
                assert!(
                    n == complete || n == complete + 1,
                    "cut at {cut} ({compression:?}): {n}"
                );
            } else {
                assert_eq!(n, complete, "cut at {cut} ({compression:?})");
            }
            assert!(n >= previous, "more bytes never yield fewer messages");
            previous = n;
            assert_eq!(
                seqs(&events),
                all_seqs[..n],
                "the yielded messages are the file's first ones"
            );
            if cut == bytes.len() {
                assert!(err.is_none());
                continue;
            }
            let err = err.unwrap_or_else(|| panic!("no error for a cut at {cut}"));
            match &err {
                CaptureError::Truncated {
                    file_len, messages, ..
                } => {
                    assert_eq!(*file_len, cut64);
                    assert_eq!(*messages as usize, n);
                    assert!(
                        err.to_string().contains(&format!("ends at byte {cut}")),
                        "{err}"
                    );
                }
                other => panic!("cut at {cut}: expected a truncation error, got {other}"),
            }
        }
    }
}

#[test]
fn not_mcap_is_named() {
    let (events, err) = read_all(b"PK\x03\x04 this is a zip file");
    assert!(events.is_empty());
    assert!(matches!(err, Some(CaptureError::NotMcap { .. })), "{err:?}");
}

#[test]
fn writer_flushes_within_its_interval_so_an_open_file_is_readable() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("live.mcap");
    let options = WriterOptions {
        flush_interval: Duration::from_millis(50),
        ..WriterOptions::default()
    };
    let mut w = CaptureWriter::create(&path, options).unwrap();
    w.write_sensor(&sensor(), 1).unwrap();
    w.write_range(&range_frame(0), RangeEncoding::F32Metres)
        .unwrap();
    std::thread::sleep(Duration::from_millis(80));
    // An idle recorder's timer tick.
    w.flush_if_due().unwrap();
    // Read the file while the writer is still open, as after a crash.
    let bytes = std::fs::read(&path).unwrap();
    let (events, err) = read_all(&bytes);
    assert!(matches!(err, Some(CaptureError::Truncated { .. })));
    let ranges = events
        .iter()
        .filter(|e| matches!(e, CaptureEvent::Range(_)))
        .count();
    assert_eq!(ranges, 1, "the frame written before the flush survives");
    assert_eq!(events.len(), 6);
    drop(w);
}

#[test]
fn range_before_calibration_and_size_mismatch_name_topic_and_log_time() {
    let sink = SharedSink::default();
    let mut w = CaptureWriter::new(sink.clone(), WriterOptions::default(), "mem".into()).unwrap();
    let early = range_frame(0);
    w.write_range(
        &RangeFrame {
            intensity: None,
            ..early.clone()
        },
        RangeEncoding::F32Metres,
    )
    .unwrap();
    let mut small = sensor().lidar;
    small.width = 4;
    w.write_calibration(texel::capture::CameraRole::Lidar, &small, 2)
        .unwrap();
    let late = range_frame(1);
    w.write_range(
        &RangeFrame {
            intensity: None,
            ..late.clone()
        },
        RangeEncoding::F32Metres,
    )
    .unwrap();
    w.write_calibration(texel::capture::CameraRole::Lidar, &sensor().lidar, 3)
        .unwrap();
    let ok = range_frame(2);
    w.write_range(
        &RangeFrame {
            intensity: None,
            ..ok
        },
        RangeEncoding::F32Metres,
    )
    .unwrap();
    w.finish().unwrap();
    let bytes = sink.bytes();
    let items: Vec<_> = CaptureReader::new(Cursor::new(&bytes[..]), None, "mem".into()).collect();
    assert_eq!(items.len(), 5);
    let e0 = items[0].as_ref().unwrap_err().to_string();
    assert!(
        e0.contains("/lidar/range") && e0.contains(&early.timestamp_ns.to_string()),
        "{e0}"
    );
    assert!(e0.contains("before any /lidar/calibration"), "{e0}");
    let e2 = items[2].as_ref().unwrap_err().to_string();
    assert!(
        e2.contains(&late.timestamp_ns.to_string()) && e2.contains("8x6") && e2.contains("4x6"),
        "{e2}"
    );
    assert!(
        matches!(items[4], Ok(CaptureEvent::Range(_))),
        "reading goes on past violations"
    );
}
