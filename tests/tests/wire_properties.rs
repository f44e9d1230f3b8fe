//! Property tests of the viewer stream's wire format (`texel::wire`): every message
//! round-trips; any byte string decodes to a message, "incomplete" or an error without
//! panicking; and no single allocation while decoding exceeds the frame it was given
//! plus 1 KiB (error messages), however the lengths inside lie (checked with a
//! counting allocator); rebuilding a scan adds only its declared, bounded sizes and a
//! compressed texture decoder's fixed working set. A real fused scan
//! round-trips exactly with PNG and raw textures.
#![allow(clippy::unwrap_used, clippy::expect_used)]
// tests panic on failure by design
// The counting allocator must implement `GlobalAlloc`, an unsafe trait; it only
// forwards to the system allocator.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::Arc;

use proptest::prelude::*;
use texel::model::{Model, ScanListing};
use texel::pose::pose_from_parts;
use texel::tile::{MAX_LOD, TileId, TileListing};
use texel::wire::{
    Limits, MAX_NAME_LEN, Message, Status, Texture, TextureFormat, WireScan, WireTile, decode_frame,
};
use texel::{EoFrame, FuseConfig, Pose, RangeNoise, Sensor, TriangleFlags, fuse};
use texel_e2e::captures;

struct Counting;

thread_local! {
    static TRACKING: Cell<bool> = const { Cell::new(false) };
    static PEAK: Cell<usize> = const { Cell::new(0) };
}

fn note(size: usize) {
    let _ = TRACKING.try_with(|on| {
        if on.get() {
            let _ = PEAK.try_with(|p| p.set(p.get().max(size)));
        }
    });
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note(new_size);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Room for error messages beyond the frame's own size.
const SLACK: usize = 1024;

/// The fixed buffer a compressed texture's decoder holds whatever the image (PNG's
/// reader keeps 16 KiB), on top of the declared RGB size.
const DECODER_WORKING_SET: usize = 16 * 1024;

/// The largest single allocation `f` makes on this thread.
fn peak_allocation<R>(f: impl FnOnce() -> R) -> (R, usize) {
    PEAK.with(|p| p.set(0));
    TRACKING.with(|t| t.set(true));
    let r = f();
    TRACKING.with(|t| t.set(false));
    (r, PEAK.with(Cell::get))
}

fn pose_strategy() -> impl Strategy<Value = Pose> {
    (
        prop::array::uniform3(-1e7f64..1e7),
        prop::array::uniform4(-1.0f64..1.0),
    )
        .prop_filter_map("a rotation", |(t, q)| pose_from_parts(t, q).ok())
}

fn scan_strategy() -> impl Strategy<Value = WireScan> {
    (1u32..6, 1u32..5, 1u32..4, 1u32..4).prop_flat_map(|(gw, gh, tw, th)| {
        let pixels = (gw * gh) as usize;
        (0..=pixels).prop_flat_map(move |n| {
            let tri = if n == 0 {
                Just(Vec::new()).boxed()
            } else {
                prop::collection::vec(prop::array::uniform3(0..n as u32), 0..8).boxed()
            };
            (
                (
                    any::<u64>(),
                    pose_strategy(),
                    pose_strategy(),
                    any::<u64>(),
                    any::<u32>(),
                ),
                prop::collection::vec(prop::array::uniform3(-1e3f32..1e3), n),
                prop::collection::vec(prop::array::uniform2(0f32..1.0), n),
                prop::collection::vec(any::<bool>(), n),
                Just((0..pixels as u32).collect::<Vec<_>>()).prop_shuffle(),
                tri,
                prop::collection::vec(any::<u8>(), (3 * tw * th) as usize),
                (prop::array::uniform3(-1e6f64..1e6), 0f64..1.0, 0f64..0.1),
            )
                .prop_flat_map(
                    move |(head, vertices, tex_coords, textured, pixels, triangles, rgb, extra)| {
                        let m = triangles.len();
                        (
                            Just((
                                head, vertices, tex_coords, textured, pixels, triangles, rgb, extra,
                            )),
                            prop::collection::vec(0f32..=1.0, m),
                            prop::collection::vec(0u8..4, m),
                        )
                    },
                )
                .prop_map(
                    move |(
                        (
                            (id, world, scan_from_lidar, t, seq),
                            vertices,
                            tex,
                            textured,
                            pixels,
                            tris,
                            rgb,
                            (cop, s0, s1),
                        ),
                        accuracy,
                        flags,
                    )| WireScan {
                        id,
                        world_from_scan: world,
                        timestamp_ns: t,
                        seq,
                        grid_width: gw,
                        grid_height: gh,
                        scan_from_lidar,
                        cop_m: cop,
                        range_noise: RangeNoise {
                            sigma_m: s0,
                            sigma_per_m: s1,
                        },
                        vertex_pixel: pixels[..vertices.len()].to_vec(),
                        vertices,
                        tex_coords: tex,
                        vertex_textured: textured,
                        triangles: tris,
                        triangle_accuracy: accuracy,
                        triangle_flags: flags.into_iter().map(TriangleFlags).collect(),
                        texture: Texture {
                            format: TextureFormat::Rgb8,
                            width: tw,
                            height: th,
                            timestamp_ns: t,
                            data: rgb,
                        },
                    },
                )
        })
    })
}

fn name() -> impl Strategy<Value = String> {
    "[a-zA-Z0-9 éü-]{0,40}".prop_map(|s| {
        let mut s = s;
        s.truncate(MAX_NAME_LEN);
        s
    })
}

fn message_strategy() -> impl Strategy<Value = Message> {
    prop_oneof![
        (any::<u16>(), name(), name()).prop_map(|(version, token, client_name)| {
            Message::ClientHello {
                version,
                token,
                client_name,
            }
        }),
        (any::<u16>(), name(), name()).prop_map(|(version, server_name, session_name)| {
            Message::ServerHello {
                version,
                server_name,
                session_name,
            }
        }),
        name().prop_map(|reason| Message::Refused { reason }),
        any::<u64>().prop_map(|scan_count| Message::ModelReset { scan_count }),
        any::<u64>().prop_map(|scan_count| Message::SnapshotComplete { scan_count }),
        scan_strategy().prop_map(|s| Message::ScanAdded(Box::new(s))),
        (any::<u64>(), pose_strategy()).prop_map(|(id, world_from_scan)| {
            Message::PoseRevised {
                id,
                world_from_scan,
            }
        }),
        (0u64..1000, 0.0f64..1e6).prop_map(|(clients, uptime_s)| {
            Message::Status(Box::new(Status {
                uptime_s,
                clients,
                ..Status::default()
            }))
        }),
        name().prop_map(|reason| Message::Goodbye { reason }),
        (any::<u64>(), listing_strategy(), pose_strategy()).prop_map(
            |(id, listing, world_from_scan)| Message::ScanListed {
                id,
                listing,
                world_from_scan,
            }
        ),
        any::<u64>().prop_map(|id| Message::ScanWithdrawn { id }),
        (any::<u64>(), name()).prop_map(|(id, reason)| Message::ScanUnavailable { id, reason }),
        any::<u64>().prop_map(|id| Message::RequestScan { id }),
        (tile_id_strategy(), tile_listing_strategy())
            .prop_map(|(id, listing)| Message::TileListed { id, listing }),
        tile_id_strategy().prop_map(|id| Message::TileWithdrawn { id }),
        tile_id_strategy().prop_map(|id| Message::RequestTile { id }),
        (tile_id_strategy(), name())
            .prop_map(|(id, reason)| Message::TileUnavailable { id, reason }),
        (
            tile_id_strategy(),
            any::<u64>(),
            prop::collection::vec(any::<u8>(), 0..300)
        )
            .prop_map(|(id, revision, data)| Message::TileData(Box::new(WireTile {
                id,
                revision,
                data
            }))),
    ]
}

fn tile_id_strategy() -> impl Strategy<Value = TileId> {
    (0..=MAX_LOD, any::<i64>(), any::<i64>()).prop_map(|(lod, x, y)| TileId { lod, x, y })
}

/// A tile listing with bounds in order and a non-negative error.
fn tile_listing_strategy() -> impl Strategy<Value = TileListing> {
    (
        any::<u64>(),
        prop::array::uniform3((-1e7f64..1e7, -1e7f64..1e7)),
        0.0f64..1e4,
        any::<u32>(),
        any::<u64>(),
    )
        .prop_map(
            |(revision, axes, geometric_error_m, triangles, encoded_bytes)| TileListing {
                revision,
                bounds_min_m: axes.map(|(a, b)| a.min(b)),
                bounds_max_m: axes.map(|(a, b)| a.max(b)),
                geometric_error_m,
                triangles,
                encoded_bytes,
            },
        )
}

/// A listing with bounds in order: each axis's two values sorted.
fn listing_strategy() -> impl Strategy<Value = ScanListing> {
    (
        any::<u64>(),
        prop::array::uniform3((-1e6f32..1e6, -1e6f32..1e6)),
        prop::array::uniform3(-1e3f32..1e3),
        -1e9f32..1e9,
        any::<u64>(),
    )
        .prop_map(
            |(timestamp_ns, axes, cop_m, priority, encoded_bytes)| ScanListing {
                timestamp_ns,
                bounds_min_m: axes.map(|(a, b)| a.min(b)),
                bounds_max_m: axes.map(|(a, b)| a.max(b)),
                cop_m,
                priority,
                encoded_bytes,
            },
        )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    #[test]
    fn every_message_round_trips_in_any_split(m in message_strategy(), cut in any::<prop::sample::Index>()) {
        let bytes = m.encode().unwrap();
        let cut = cut.index(bytes.len());
        prop_assert_eq!(decode_frame(&bytes[..cut], &Limits::FROM_SERVER).unwrap(), None);
        let (back, used) = decode_frame(&bytes, &Limits::FROM_SERVER).unwrap().unwrap();
        prop_assert_eq!(used, bytes.len());
        prop_assert_eq!(back, m);
    }

    #[test]
    fn any_bytes_decode_without_panic_or_allocation_beyond_the_input(
        bytes in prop::collection::vec(any::<u8>(), 0..2048),
    ) {
        for limits in [Limits::FROM_CLIENT, Limits::FROM_SERVER] {
            let (result, peak) = peak_allocation(|| decode_frame(&bytes, &limits));
            if let Ok(Some((_, used))) = result {
                prop_assert!(used <= bytes.len());
            }
            prop_assert!(peak <= bytes.len() + SLACK, "{} bytes allocated for {}", peak, bytes.len());
        }
    }

    #[test]
    fn framed_garbage_of_every_kind_decodes_without_panic_or_allocation_beyond_it(
        kind in prop_oneof![0u8..4, 0x10u8..0x17, Just(0x20u8), Just(0x30u8), Just(0x40u8), any::<u8>()],
        body in prop::collection::vec(any::<u8>(), 0..512),
    ) {
        // A correct length prefix, so the kind's own decoder sees the garbage.
        let mut bytes = ((body.len() + 1) as u32).to_le_bytes().to_vec();
        bytes.push(kind);
        bytes.extend(&body);
        let (result, peak) = peak_allocation(|| decode_frame(&bytes, &Limits::FROM_SERVER));
        prop_assert!(!matches!(result, Ok(None)), "a complete frame is never incomplete");
        prop_assert!(peak <= bytes.len() + SLACK, "{} bytes allocated for {}", peak, bytes.len());
    }

    /// A listing of any floats encodes exactly when the decoder would accept it:
    /// every number finite and each axis's bounds in order; then it round-trips.
    #[test]
    fn listings_encode_exactly_when_they_are_valid_and_then_round_trip(
        floats in prop::array::uniform10(prop_oneof![
            any::<f32>(),
            Just(f32::NAN),
            Just(f32::INFINITY),
            -10.0f32..10.0,
        ]),
        id in any::<u64>(),
    ) {
        let listing = ScanListing {
            timestamp_ns: 1,
            bounds_min_m: [floats[0], floats[1], floats[2]],
            bounds_max_m: [floats[3], floats[4], floats[5]],
            cop_m: [floats[6], floats[7], floats[8]],
            priority: floats[9],
            encoded_bytes: 2,
        };
        let valid = floats.iter().all(|v| v.is_finite())
            && (0..3).all(|k| floats[k] <= floats[k + 3]);
        let m = Message::ScanListed { id, listing, world_from_scan: Pose::identity() };
        match m.encode() {
            Ok(bytes) => {
                prop_assert!(valid, "{listing:?} encoded");
                let (back, _) = decode_frame(&bytes, &Limits::FROM_SERVER).unwrap().unwrap();
                prop_assert_eq!(back, m);
            }
            Err(_) => prop_assert!(!valid, "{listing:?} refused"),
        }
    }

    #[test]
    fn damaged_scans_never_allocate_beyond_their_frame(
        scan in scan_strategy(),
        damage in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..6),
    ) {
        let mut bytes = Message::ScanAdded(Box::new(scan)).encode().unwrap();
        for (at, value) in damage {
            let i = at.index(bytes.len());
            bytes[i] = value;
        }
        let (result, peak) = peak_allocation(|| decode_frame(&bytes, &Limits::FROM_SERVER));
        // A damaged length field may make the frame look incomplete; else it is a
        // message or an error, and never costs more memory than it holds.
        if let Ok(Some((Message::ScanAdded(s), _))) = result {
            // Rebuilding the scan allocates what the (validated, bounded) grid and
            // texture sizes declare, and no more.
            // A damaged format byte may turn the raw texture into a "compressed"
            // one, whose decoder also holds its fixed working set.
            let declared = 4 * (s.grid_width * s.grid_height) as usize
                + 3 * (s.texture.width * s.texture.height) as usize;
            let working_set = match s.texture.format {
                TextureFormat::Rgb8 => 0,
                TextureFormat::Png | TextureFormat::Jpeg => DECODER_WORKING_SET,
            };
            let (r, texture_peak) = peak_allocation(|| s.into_scan());
            prop_assert!(r.is_ok() || r.is_err());
            prop_assert!(
                texture_peak <= bytes.len() + declared + SLACK + working_set,
                "{} bytes allocated rebuilding a {}-byte frame", texture_peak, bytes.len()
            );
        }
        prop_assert!(peak <= bytes.len() + SLACK, "{} bytes allocated for {}", peak, bytes.len());
    }
}

#[test]
fn lengths_that_lie_are_refused_before_allocating() {
    // A scan claiming a million vertices in a 300-byte frame.
    let scan = WireScan::from_scan(0, &fused(), Pose::identity(), TextureFormat::Rgb8, 90).unwrap();
    let mut bytes = Message::ScanAdded(Box::new(scan)).encode().unwrap();
    // The vertex count follows the fixed-size header fields.
    let at = 4 + 1 + 8 + 56 + 8 + 4 + 4 + 4 + 56 + 24 + 16;
    bytes[at..at + 4].copy_from_slice(&(1u32 << 20).to_le_bytes());
    let (result, peak) = peak_allocation(|| decode_frame(&bytes, &Limits::FROM_SERVER));
    let e = result.unwrap_err().to_string();
    assert!(e.contains("vertex_count"), "{e}");
    assert!(peak <= SLACK, "{peak}");
    // A frame length past the limit is refused from its 4 bytes.
    let e = decode_frame(&(200u32 << 20).to_le_bytes(), &Limits::FROM_SERVER).unwrap_err();
    assert!(e.to_string().contains("frame length"), "{e}");
}

fn fused() -> texel::TexelScan {
    let m = captures::sensor();
    let (r, eo) = captures::frame(&m, 3, 1_000);
    fuse(&r, eo, &Sensor::new(m), &FuseConfig::default()).unwrap()
}

#[test]
fn a_fused_scan_round_trips_exactly_with_lossless_textures_and_closely_with_jpeg() {
    let scan = fused();
    assert!(scan.usable_triangle_count() > 0);
    let pose = pose_from_parts([5.0e6, 4.2e6, 120.0], [0.1, -0.2, 0.3, 0.9]).unwrap();
    for format in [TextureFormat::Rgb8, TextureFormat::Png, TextureFormat::Jpeg] {
        let wire = WireScan::from_scan(7, &scan, pose, format, 95).unwrap();
        let bytes = Message::ScanAdded(Box::new(wire)).encode().unwrap();
        let Some((Message::ScanAdded(back), _)) =
            decode_frame(&bytes, &Limits::FROM_SERVER).unwrap()
        else {
            panic!("not a scan");
        };
        let (id, got, got_pose) = back.into_scan().unwrap();
        assert_eq!((id, got_pose), (7, pose));
        let mut model = Model::new();
        model
            .apply(texel::model::ModelEvent::ScanAdded {
                id: 0,
                scan: Arc::new(got.clone()),
                world_from_scan: got_pose,
            })
            .unwrap();
        if format == TextureFormat::Jpeg {
            let EoFrame { rgb, .. } = &*got.texture;
            let mean = rgb
                .iter()
                .zip(&scan.texture.rgb)
                .map(|(a, b)| f64::from(a.abs_diff(*b)))
                .sum::<f64>()
                / rgb.len() as f64;
            assert!(mean < 3.0, "JPEG mean error {mean}");
            let mut same = got.clone();
            same.texture = scan.texture.clone();
            assert_eq!(same, scan);
        } else {
            assert_eq!(got, scan, "{format:?}");
        }
    }
}

#[test]
fn a_texture_whose_image_header_claims_more_is_refused_before_decoding() {
    // A 2048 x 2048 PNG (12 MiB of pixels) sent as an 8 x 4 texture.
    let frame = EoFrame {
        width: 2048,
        height: 2048,
        rgb: vec![90; 3 * 2048 * 2048],
        timestamp_ns: 0,
        exposure: None,
    };
    let mut t = Texture::encode(&frame, TextureFormat::Png, 90).unwrap();
    (t.width, t.height) = (8, 4);
    let (r, peak) = peak_allocation(|| t.decode());
    let e = r.unwrap_err().to_string();
    assert!(e.contains("header says 2048x2048"), "{e}");
    // The image reader's buffer, not the 12 MiB of pixels.
    assert!(peak <= 256 * 1024, "{peak} bytes allocated");
}

#[test]
fn compressed_textures_decode_within_their_size_plus_a_fixed_working_set() {
    // Whole, truncated and garbage PNG and JPEG textures of growing size: decoding
    // allocates at most the declared RGB size or the data, plus the decoder's fixed
    // working set, however the data lies.
    for format in [TextureFormat::Png, TextureFormat::Jpeg] {
        for (w, h) in [(2u32, 3u32), (64, 64), (640, 480)] {
            let rgb: Vec<u8> = (0..(3 * w * h) as usize)
                .map(|i| (i * 7919 % 251) as u8)
                .collect();
            let frame = EoFrame {
                width: w,
                height: h,
                rgb,
                timestamp_ns: 0,
                exposure: None,
            };
            let whole = Texture::encode(&frame, format, 90).unwrap();
            let n = whole.data.len();
            let garbage: Vec<u8> = (0..n).map(|i| (i * 131 % 256) as u8).collect();
            for data in [
                whole.data.clone(),
                whole.data[..n / 2].to_vec(),
                whole.data[..n - 1].to_vec(),
                garbage,
            ] {
                let bound = data.len() + 3 * (w * h) as usize + SLACK + DECODER_WORKING_SET;
                let texture = Texture {
                    data,
                    ..whole.clone()
                };
                let (result, peak) = peak_allocation(|| texture.decode());
                assert!(peak <= bound, "{format:?} {w}x{h}: {peak} > {bound}");
                if texture.data == whole.data {
                    assert_eq!(result.unwrap().width, w);
                }
            }
        }
    }
}
