//! Interop with the reference Python MCAP tooling, both ways: captures written by the
//! PyPI `mcap` + `mcap-protobuf-support` + `foxglove-schemas-protobuf` packages read
//! back here with identical pixels, timestamps, calibration and extrinsic, and
//! captures written here decode in Python with the Foxglove protobuf classes.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::ffi::OsStr;

use serde_json::Value;
use texel::capture::{
    CaptureWriter, EoEncoding, PoseAnchor, PoseTopic, RangeEncoding, TexelItem, WriterOptions,
    open_texel_frames,
};
use texel::pose::{pose_from_parts, pose_to_parts};
use texel::{Distortion, EoFrame, PinholeCamera, PlumbBob, RangeFrame, RangeNoise, SensorModel};
use texel_e2e::run_python;

fn f64s(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

#[test]
fn python_written_captures_read_back_identically() {
    let dir = tempfile::tempdir().unwrap();
    for compression in ["zstd", "lz4", "none"] {
        let capture = dir.path().join(format!("py-{compression}.mcap"));
        let expected_path = dir.path().join(format!("py-{compression}.json"));
        run_python(
            "write_capture.py",
            &[
                capture.as_os_str(),
                expected_path.as_os_str(),
                OsStr::new("--compression"),
                OsStr::new(compression),
            ],
        );
        let expected: Value =
            serde_json::from_str(&std::fs::read_to_string(&expected_path).unwrap()).unwrap();

        let mut pairs = Vec::new();
        let mut poses = Vec::new();
        let mut sensor = None;
        for item in open_texel_frames(&capture).unwrap() {
            match item.unwrap() {
                TexelItem::Pair { pair, sensor: s } => {
                    sensor = Some(s);
                    pairs.push(pair);
                }
                TexelItem::Pose {
                    topic,
                    timestamp_ns,
                    world_from_eo,
                } => {
                    assert_eq!(topic, PoseTopic::Truth);
                    poses.push((timestamp_ns, world_from_eo));
                }
                TexelItem::Anchor(a) => panic!("the Python capture has no anchors: {a:?}"),
            }
        }
        let sensor = sensor.expect("a sensor model");
        // Calibration and extrinsic, exactly.
        assert_eq!(
            sensor.lidar.k_row_major().to_vec(),
            f64s(&expected["lidar_k"])
        );
        assert_eq!(sensor.eo.k_row_major().to_vec(), f64s(&expected["eo_k"]));
        assert_eq!(sensor.eo.distortion_fields().1, f64s(&expected["eo_d"]));
        let (t, q) = pose_to_parts(&sensor.eo_from_lidar);
        assert_eq!(t.to_vec(), f64s(&expected["eo_from_lidar"]["t"]));
        for (a, b) in q.iter().zip(f64s(&expected["eo_from_lidar"]["q"])) {
            assert!((a - b).abs() < 1e-15);
        }
        let s = &expected["sensor"];
        assert_eq!(
            sensor.range_noise.sigma_m,
            s["range_noise_sigma_m"].as_f64().unwrap()
        );
        assert_eq!(
            sensor.range_noise.sigma_per_m,
            s["range_noise_sigma_per_m"].as_f64().unwrap()
        );
        assert_eq!(sensor.min_range_m, 0.5);
        assert_eq!(sensor.max_range_m, 40.0);
        assert_eq!(sensor.name, "python interop");

        let frames = expected["frames"].as_array().unwrap();
        assert_eq!(pairs.len(), frames.len(), "{compression}");
        for (pair, f) in pairs.iter().zip(frames) {
            let t = f["t_ns"].as_u64().unwrap();
            assert_eq!(pair.range.timestamp_ns, t);
            assert_eq!(pair.eo.timestamp_ns, t);
            for (got, want) in pair
                .range
                .ranges_m
                .iter()
                .zip(f["ranges_m"].as_array().unwrap())
            {
                match want.as_f64() {
                    None => assert!(got.is_nan()),
                    Some(w) if f["range_encoding"] == "32FC1" => assert_eq!(*got, w as f32),
                    Some(w) => assert!((f64::from(*got) - w).abs() < 1e-6, "{got} vs {w}"),
                }
            }
            let intensity: Vec<f32> = f64s(&f["intensity"])
                .into_iter()
                .map(|v| v as f32)
                .collect();
            assert_eq!(pair.range.intensity.as_ref(), Some(&intensity));
            let encoding = f["eo_encoding"].as_str().unwrap();
            assert_eq!((pair.eo.width, pair.eo.height), (32, 24));
            match f["exposure"].as_object() {
                Some(want) => {
                    let got = pair.eo.exposure.expect("the frame's /eo/exposure");
                    assert_eq!(
                        got.exposure_time_s,
                        want["exposure_time_s"].as_f64().unwrap()
                    );
                    assert_eq!(got.gain, want["gain"].as_f64().unwrap());
                }
                None => assert_eq!(pair.eo.exposure, None, "{encoding}"),
            }
            match f["rgb"].as_array() {
                Some(rgb) => {
                    let want: Vec<u8> = rgb.iter().map(|v| v.as_u64().unwrap() as u8).collect();
                    // YUYV goes through floating-point colour conversion on both
                    // sides: one count of rounding is allowed there, none elsewhere.
                    let tolerance = if encoding == "yuyv" { 1 } else { 0 };
                    for (a, b) in pair.eo.rgb.iter().zip(&want) {
                        assert!(a.abs_diff(*b) <= tolerance, "{encoding}: {a} vs {b}");
                    }
                }
                None => assert_eq!(encoding, "jpeg"),
            }
        }
        assert_eq!(poses.len(), frames.len());
        for ((t, pose), p) in poses.iter().zip(expected["poses"].as_array().unwrap()) {
            assert_eq!(*t, p["t_ns"].as_u64().unwrap());
            assert_eq!(
                pose.translation.vector.as_slice(),
                f64s(&p["translation"]).as_slice()
            );
        }
    }
}

#[test]
fn captures_written_here_decode_in_python() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("rust.mcap");
    let model = SensorModel {
        name: "rust interop".into(),
        lidar: PinholeCamera {
            width: 10,
            height: 4,
            fx: 11.0,
            fy: 12.0,
            cx: 4.5,
            cy: 1.5,
            skew: 0.0,
            distortion: Distortion::None,
        },
        eo: PinholeCamera {
            width: 12,
            height: 6,
            fx: 30.0,
            fy: 31.0,
            cx: 5.5,
            cy: 2.5,
            skew: 0.0,
            distortion: Distortion::PlumbBob(PlumbBob {
                k1: -0.2,
                k2: 0.05,
                p1: 0.001,
                p2: 0.002,
                k3: -0.003,
            }),
        },
        eo_from_lidar: pose_from_parts([0.01, 0.02, 0.03], [0.0, 0.0, 0.0087265, 0.9999619])
            .unwrap(),
        range_noise: RangeNoise {
            sigma_m: 0.003,
            sigma_per_m: 0.0005,
        },
        range_bias_m: 0.0,
        min_range_m: 0.2,
        max_range_m: 50.0,
        eo_response: None,
    };
    let t0 = 1_750_000_000_123_456_789u64;
    let mut w = CaptureWriter::create(&capture, WriterOptions::default()).unwrap();
    w.write_sensor(&model, t0).unwrap();
    let mut ranges = Vec::new();
    let mut rgbs = Vec::new();
    let mut anchors = Vec::new();
    for (i, eo_encoding) in EoEncoding::ALL.iter().enumerate() {
        let t = t0 + (i as u64 + 1) * 50_000_000;
        let mut r = RangeFrame::empty(10, 4, t, i as u32);
        for (k, v) in r.ranges_m.iter_mut().enumerate() {
            if k % 3 != 0 {
                *v = 1.5 + 0.25 * k as f32;
            }
        }
        r.intensity = Some((0..40).map(|k| (k * 3 + i) as f32).collect());
        let encoding = if i % 2 == 0 {
            RangeEncoding::F32Metres
        } else {
            RangeEncoding::U16Millimetres
        };
        w.write_range(&r, encoding).unwrap();
        let e = EoFrame {
            width: 12,
            height: 6,
            rgb: (0..216).map(|k| (k * 5 + i) as u8).collect(),
            timestamp_ns: t,
            exposure: Some(texel::EoExposure {
                exposure_time_s: 0.001 * (i as f64 + 1.0),
                gain: 2.0,
            }),
        };
        w.write_eo(&e, *eo_encoding).unwrap();
        w.write_pose(
            PoseTopic::Texel,
            t,
            &pose_from_parts([i as f64, 1.0, 2.0], [0.0, 0.0, 0.0, 1.0]).unwrap(),
        )
        .unwrap();
        // Every frame hangs from the first (itself, for the first).
        let anchor = PoseAnchor {
            timestamp_ns: t,
            keyframe_timestamp_ns: t0,
            keyframe_from_eo: pose_from_parts([i as f64, 0.0, 0.0], [0.0, 0.0, 0.6, 0.8]).unwrap(),
        };
        w.write_anchor(&anchor, t).unwrap();
        anchors.push(anchor);
        ranges.push((r, encoding));
        rgbs.push((e, *eo_encoding));
    }
    w.finish().unwrap();

    let out = run_python("read_capture.py", &[capture.as_os_str()]);
    let got: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(got["profile"], "");
    assert_eq!(got["topics"]["/lidar/range"], 5);
    assert_eq!(got["topics"]["/lidar/intensity"], 5);
    assert_eq!(got["topics"]["/eo/image"], 5);
    assert_eq!(got["topics"]["/texel/pose"], 5);
    assert_eq!(
        got["schemas"]["/texel/anchor"],
        serde_json::json!(["texel.Anchor", "jsonschema", "json"])
    );
    for (a, g) in anchors.iter().zip(got["anchors"].as_array().unwrap()) {
        let ns =
            |v: &Value| v["sec"].as_u64().unwrap() * 1_000_000_000 + v["nsec"].as_u64().unwrap();
        assert_eq!(ns(&g["timestamp"]), a.timestamp_ns);
        assert_eq!(ns(&g["keyframe"]), a.keyframe_timestamp_ns);
        assert_eq!(g["log_time"].as_u64().unwrap(), a.timestamp_ns);
        let (t, q) = pose_to_parts(&a.keyframe_from_eo);
        let r = &g["rotation"];
        assert_eq!(
            [
                &g["translation"]["x"],
                &g["translation"]["y"],
                &g["translation"]["z"]
            ]
            .map(|v| v.as_f64().unwrap()),
            t
        );
        assert_eq!(
            [&r["x"], &r["y"], &r["z"], &r["w"]].map(|v| v.as_f64().unwrap()),
            q
        );
    }
    assert_eq!(got["anchors"].as_array().unwrap().len(), 5);
    assert_eq!(
        got["schemas"]["/eo/exposure"],
        serde_json::json!(["texel.EoExposure", "jsonschema", "json"])
    );
    let exposures = got["exposures"].as_array().unwrap();
    assert_eq!(exposures.len(), rgbs.len());
    for ((e, _), g) in rgbs.iter().zip(exposures) {
        let ns =
            |v: &Value| v["sec"].as_u64().unwrap() * 1_000_000_000 + v["nsec"].as_u64().unwrap();
        let want = e.exposure.unwrap();
        assert_eq!(ns(&g["timestamp"]), e.timestamp_ns);
        assert_eq!(g["log_time"].as_u64().unwrap(), e.timestamp_ns);
        assert_eq!(g["exposure_time_s"].as_f64().unwrap(), want.exposure_time_s);
        assert_eq!(g["gain"].as_f64().unwrap(), want.gain);
    }
    assert_eq!(got["schemas"]["/lidar/range"][0], "foxglove.RawImage");
    assert_eq!(
        got["schemas"]["/texel/sensor"],
        serde_json::json!(["texel.Sensor", "jsonschema", "json"])
    );
    assert_eq!(got["sensor"]["range_noise_sigma_m"], 0.003);
    assert_eq!(got["sensor"]["name"], "rust interop");
    let eo_cal = &got["calibrations"]["/eo/calibration"];
    assert_eq!(f64s(&eo_cal["K"]), model.eo.k_row_major().to_vec());
    assert_eq!(f64s(&eo_cal["D"]), model.eo.distortion_fields().1);
    assert_eq!(eo_cal["model"], "plumb_bob");
    assert_eq!(eo_cal["frame_id"], "eo");
    let tf = &got["poses"]["/tf_static"][0];
    assert_eq!(
        (tf["parent"].as_str(), tf["child"].as_str()),
        (Some("eo"), Some("lidar"))
    );
    let (t, q) = pose_to_parts(&model.eo_from_lidar);
    assert_eq!(f64s(&tf["t"]), t.to_vec());
    assert_eq!(f64s(&tf["q"]), q.to_vec());
    assert_eq!(tf["t_ns"], t0);

    for ((r, encoding), g) in ranges.iter().zip(got["range"].as_array().unwrap()) {
        assert_eq!(g["t_ns"].as_u64().unwrap(), r.timestamp_ns);
        assert_eq!(
            g["log_time"].as_u64().unwrap(),
            r.timestamp_ns,
            "log time = timestamp"
        );
        assert_eq!(g["encoding"], encoding.name());
        assert_eq!(g["frame_id"], "lidar");
        for (v, want) in g["values"].as_array().unwrap().iter().zip(&r.ranges_m) {
            match encoding {
                RangeEncoding::F32Metres => match v.as_f64() {
                    None => assert!(want.is_nan()),
                    Some(x) => assert_eq!(x as f32, *want),
                },
                RangeEncoding::U16Millimetres => {
                    let mm = v.as_u64().unwrap();
                    if want.is_nan() {
                        assert_eq!(mm, 0);
                    } else {
                        assert_eq!(mm, (f64::from(*want) * 1000.0).round() as u64);
                    }
                }
            }
        }
    }
    for ((r, _), g) in ranges.iter().zip(got["intensity"].as_array().unwrap()) {
        let want: Vec<f64> = r
            .intensity
            .as_ref()
            .unwrap()
            .iter()
            .map(|&v| f64::from(v))
            .collect();
        assert_eq!(f64s(&g["values"]), want);
        assert_eq!(g["encoding"], "mono16");
    }
    for ((e, encoding), g) in rgbs.iter().zip(got["eo"].as_array().unwrap()) {
        assert_eq!(g["encoding"], encoding.name());
        let data: Vec<u8> = g["data"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap() as u8)
            .collect();
        let (step, want) = texel::capture::encode_eo(&e.rgb, 12, 6, *encoding).unwrap();
        assert_eq!(g["step"].as_u64().unwrap(), u64::from(step));
        assert_eq!(data, want);
    }
}

/// The worked example in docs/capture-format.md runs and writes a capture that reads
/// back as one texel frame with the sensor it describes.
#[test]
fn the_documented_python_example_writes_a_valid_capture() {
    let doc =
        std::fs::read_to_string(texel_e2e::repo_root().join("docs/capture-format.md")).unwrap();
    let start = doc.find("```python\n").expect("a python example") + "```python\n".len();
    let end = start + doc[start..].find("```").unwrap();
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("example.py"), &doc[start..end]).unwrap();
    let status = std::process::Command::new(texel_e2e::python())
        .arg("example.py")
        .current_dir(dir.path())
        .status()
        .unwrap();
    assert!(status.success());
    let items: Vec<_> = open_texel_frames(&dir.path().join("one-frame.mcap"))
        .unwrap()
        .collect();
    assert_eq!(items.len(), 1);
    let Ok(TexelItem::Pair { pair, sensor }) = &items[0] else {
        panic!("{:?}", items[0])
    };
    assert_eq!(pair.range.return_count(), 120 * 128);
    assert_eq!(pair.eo.pixel(5, 5), Some([200, 0, 0]));
    assert_eq!(sensor.eo_from_lidar.translation.vector.x, 0.03);
    assert_eq!(sensor.range_noise.sigma_m, 0.01);
}
