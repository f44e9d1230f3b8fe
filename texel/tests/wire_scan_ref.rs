//! `ScanAdded` written from a borrowed scan (`WireScanRef`) against the owned path
//! (`WireScan::with_texture`, `Message::encode`) and against a reference encoder of
//! the wire layout kept here as it was first written: the bytes are identical, and
//! the decoder gives back the owned message. `check_sendable` accepts exactly the
//! scans whose frames the decoder accepts, and allocates nothing for a scan it
//! accepts; encoding from the borrowed scan allocates once, exactly the frame's length
//! (checked with a counting allocator).
#![allow(clippy::unwrap_used, clippy::expect_used)]
// tests panic on failure by design
// The counting allocator must implement `GlobalAlloc`, an unsafe trait; it only
// forwards to the system allocator.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::Arc;

use proptest::prelude::*;
use texel::pose::{pose_from_parts, pose_to_parts};
use texel::scan::NO_VERTEX;
use texel::wire::{
    Limits, Message, Texture, TextureFormat, TextureRef, WireScan, WireScanRef, check_sendable,
    decode_frame,
};
use texel::{
    EoFrame, FuseConfig, PinholeCamera, Pose, RangeFrame, RangeNoise, Sensor, SensorModel,
    TexelScan, TriangleFlags, fuse,
};

struct Counting;

thread_local! {
    static TRACKING: Cell<bool> = const { Cell::new(false) };
    static COUNT: Cell<usize> = const { Cell::new(0) };
    static BYTES: Cell<usize> = const { Cell::new(0) };
}

fn note(size: usize) {
    let _ = TRACKING.try_with(|on| {
        if on.get() {
            let _ = COUNT.try_with(|c| c.set(c.get() + 1));
            let _ = BYTES.try_with(|b| b.set(b.get() + size));
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

/// The allocations `f` makes on this thread: how many, and their bytes in total.
fn allocations<R>(f: impl FnOnce() -> R) -> (R, usize, usize) {
    COUNT.with(|c| c.set(0));
    BYTES.with(|b| b.set(0));
    TRACKING.with(|t| t.set(true));
    let r = f();
    TRACKING.with(|t| t.set(false));
    (r, COUNT.with(Cell::get), BYTES.with(Cell::get))
}

/// The `ScanAdded` frame as the wire format lays it out (`docs/wire-protocol.md`),
/// written field by field with no checks: the layout the other encoders must keep.
fn reference_frame(w: &WireScan) -> Vec<u8> {
    fn pose(out: &mut Vec<u8>, p: &Pose) {
        let (t, q) = pose_to_parts(p);
        for v in t.iter().chain(q.iter()) {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    let mut out = vec![0u8; 4];
    out.push(0x12);
    out.extend_from_slice(&w.id.to_le_bytes());
    pose(&mut out, &w.world_from_scan);
    out.extend_from_slice(&w.timestamp_ns.to_le_bytes());
    out.extend_from_slice(&w.seq.to_le_bytes());
    out.extend_from_slice(&w.grid_width.to_le_bytes());
    out.extend_from_slice(&w.grid_height.to_le_bytes());
    pose(&mut out, &w.scan_from_lidar);
    for v in w.cop_m {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&w.range_noise.sigma_m.to_le_bytes());
    out.extend_from_slice(&w.range_noise.sigma_per_m.to_le_bytes());
    out.extend_from_slice(&(w.vertices.len() as u32).to_le_bytes());
    for v in w.vertices.iter().flatten() {
        out.extend_from_slice(&v.to_le_bytes());
    }
    for v in w.tex_coords.iter().flatten() {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend(w.vertex_textured.iter().map(|&t| u8::from(t)));
    for p in &w.vertex_pixel {
        out.extend_from_slice(&p.to_le_bytes());
    }
    out.extend_from_slice(&(w.triangles.len() as u32).to_le_bytes());
    for i in w.triangles.iter().flatten() {
        out.extend_from_slice(&i.to_le_bytes());
    }
    for a in &w.triangle_accuracy {
        out.extend_from_slice(&a.to_le_bytes());
    }
    out.extend(w.triangle_flags.iter().map(|f| f.0));
    out.push(match w.texture.format {
        TextureFormat::Rgb8 => 0,
        TextureFormat::Png => 1,
        TextureFormat::Jpeg => 2,
    });
    out.extend_from_slice(&w.texture.width.to_le_bytes());
    out.extend_from_slice(&w.texture.height.to_le_bytes());
    out.extend_from_slice(&w.texture.timestamp_ns.to_le_bytes());
    out.extend_from_slice(&(w.texture.data.len() as u32).to_le_bytes());
    out.extend_from_slice(&w.texture.data);
    let body_len = (out.len() - 4) as u32;
    out[..4].copy_from_slice(&body_len.to_le_bytes());
    out
}

/// A scan's fields as an owned message, copied without any check (so a broken scan
/// can be written with [`reference_frame`] and shown to the decoder).
fn unchecked_wire(id: u64, scan: &TexelScan, world: Pose, texture: Texture) -> WireScan {
    WireScan {
        id,
        world_from_scan: world,
        timestamp_ns: scan.timestamp_ns,
        seq: scan.seq,
        grid_width: scan.grid_width,
        grid_height: scan.grid_height,
        scan_from_lidar: scan.scan_from_lidar,
        cop_m: scan.cop_m,
        range_noise: scan.range_noise,
        vertices: scan.vertices.clone(),
        tex_coords: scan.tex_coords.clone(),
        vertex_textured: scan.vertex_textured.clone(),
        vertex_pixel: scan.vertex_pixel.clone(),
        triangles: scan.triangles.clone(),
        triangle_accuracy: scan.triangle_accuracy.clone(),
        triangle_flags: scan.triangle_flags.clone(),
        texture,
    }
}

/// The scan's own pixels as a raw texture (what `check_sendable` vouches for).
fn raw_texture(frame: &EoFrame) -> Texture {
    Texture {
        format: TextureFormat::Rgb8,
        width: frame.width,
        height: frame.height,
        timestamp_ns: frame.timestamp_ns,
        data: frame.rgb.clone(),
    }
}

fn pose_strategy() -> impl Strategy<Value = Pose> {
    (
        prop::array::uniform3(-1e7f64..1e7),
        prop::array::uniform4(-1.0f64..1.0),
    )
        .prop_filter_map("a rotation", |(t, q)| pose_from_parts(t, q).ok())
}

/// Small scans that keep every rule of the wire.
fn scan_strategy() -> impl Strategy<Value = TexelScan> {
    (1u32..6, 1u32..5, 1u32..4, 1u32..4).prop_flat_map(|(gw, gh, tw, th)| {
        let pixels = (gw * gh) as usize;
        (0..=pixels).prop_flat_map(move |n| {
            let triangles = if n == 0 {
                Just(Vec::new()).boxed()
            } else {
                prop::collection::vec(prop::array::uniform3(0..n as u32), 0..8).boxed()
            };
            (
                (pose_strategy(), any::<u64>(), any::<u32>(), any::<u64>()),
                prop::collection::vec(prop::array::uniform3(-1e3f32..1e3), n),
                prop::collection::vec(prop::array::uniform2(0f32..1.0), n),
                prop::collection::vec(any::<bool>(), n),
                Just((0..pixels as u32).collect::<Vec<_>>()).prop_shuffle(),
                triangles,
                prop::collection::vec(any::<u8>(), (3 * tw * th) as usize),
                (prop::array::uniform3(-1e6f64..1e6), 0f64..1.0, 0f64..0.1),
            )
                .prop_flat_map(|parts| {
                    let m = parts.5.len();
                    (
                        Just(parts),
                        prop::collection::vec(0f32..=1.0, m),
                        prop::collection::vec(0u8..4, m),
                    )
                })
                .prop_map(
                    move |(
                        (
                            (scan_from_lidar, t, seq, t_eo),
                            vertices,
                            tex_coords,
                            vertex_textured,
                            order,
                            triangles,
                            rgb,
                            (cop_m, sigma_m, sigma_per_m),
                        ),
                        triangle_accuracy,
                        flags,
                    )| {
                        let vertex_pixel: Vec<u32> = order[..n].to_vec();
                        let mut pixel_vertex = vec![NO_VERTEX; pixels];
                        for (v, &p) in vertex_pixel.iter().enumerate() {
                            pixel_vertex[p as usize] = v as u32;
                        }
                        TexelScan {
                            timestamp_ns: t,
                            seq,
                            grid_width: gw,
                            grid_height: gh,
                            vertices,
                            tex_coords,
                            vertex_textured,
                            vertex_pixel,
                            pixel_vertex,
                            triangles,
                            triangle_accuracy,
                            triangle_flags: flags.into_iter().map(TriangleFlags).collect(),
                            texture: Arc::new(EoFrame {
                                width: tw,
                                height: th,
                                rgb,
                                timestamp_ns: t_eo,
                                exposure: None,
                            }),
                            cop_m,
                            scan_from_lidar,
                            range_noise: RangeNoise {
                                sigma_m,
                                sigma_per_m,
                            },
                        }
                    },
                )
        })
    })
}

/// The `ScanAdded` frame of `scan` by the owned path: the scan's arrays copied into a
/// `WireScan`, checked, and encoded through `Message`.
fn owned_frame(id: u64, scan: &TexelScan, world: Pose, texture: &Texture) -> Vec<u8> {
    let wire = WireScan::with_texture(id, scan, world, texture.clone()).unwrap();
    Message::ScanAdded(Box::new(wire)).encode().unwrap()
}

/// The same frame written from the borrowed scan.
fn borrowed_frame(id: u64, scan: &TexelScan, world: Pose, texture: &Texture) -> Vec<u8> {
    let view = WireScanRef::new(id, scan, world, texture.view()).unwrap();
    let bytes = view.encode().unwrap();
    assert_eq!(bytes.len(), view.frame_len());
    assert_eq!(
        bytes.capacity(),
        bytes.len(),
        "one allocation of the exact size"
    );
    bytes
}

fn texture_of(scan: &TexelScan, format: TextureFormat) -> Texture {
    Texture::encode(&scan.texture, format, 90).unwrap()
}

fn check_same_bytes(id: u64, scan: &TexelScan, world: Pose, format: TextureFormat) {
    let texture = texture_of(scan, format);
    let owned = owned_frame(id, scan, world, &texture);
    let borrowed = borrowed_frame(id, scan, world, &texture);
    assert_eq!(owned, borrowed);
    let reference = reference_frame(&unchecked_wire(id, scan, world, texture.clone()));
    assert_eq!(borrowed, reference);
    // A raw texture borrowed from the scan's own pixels writes the same bytes as one
    // copied into a `Texture`.
    if format == TextureFormat::Rgb8 {
        let view = WireScanRef::new(id, scan, world, TextureRef::rgb8(&scan.texture).unwrap());
        assert_eq!(view.unwrap().encode().unwrap(), borrowed);
    }
    // The decoder reads the borrowed path's bytes as the owned message.
    let (message, used) = decode_frame(&borrowed, &Limits::FROM_SERVER)
        .unwrap()
        .unwrap();
    assert_eq!(used, borrowed.len());
    let Message::ScanAdded(decoded) = message else {
        panic!("decoded {}", message.kind_name());
    };
    assert_eq!(
        *decoded,
        WireScan::with_texture(id, scan, world, texture).unwrap()
    );
}

/// A small sensor and a frame of a wavy wall with a step, fused: a scan with
/// stretched triangles, untextured vertices and no-returns.
fn fused_scan() -> TexelScan {
    let model = SensorModel {
        name: "wire-test".into(),
        lidar: PinholeCamera::from_vertical_fov(48, 36, 40.0).unwrap(),
        eo: PinholeCamera::from_vertical_fov(160, 120, 35.0).unwrap(),
        eo_from_lidar: Pose::translation(0.05, 0.0, 0.0),
        range_noise: RangeNoise {
            sigma_m: 0.01,
            sigma_per_m: 0.001,
        },
        range_bias_m: 0.0,
        min_range_m: 0.1,
        max_range_m: 50.0,
        eo_response: None,
    };
    let mut range = RangeFrame::empty(48, 36, 1_000, 7);
    for v in 0..36u32 {
        for u in 0..48u32 {
            let wave = 0.3 * (f64::from(u) / 5.0).sin() + 0.2 * (f64::from(v) / 7.0).cos();
            let step = if u > 30 { 1.5 } else { 0.0 };
            if (u * 7 + v * 3) % 29 != 0 {
                range.ranges_m[(v * 48 + u) as usize] = (4.0 + wave + step) as f32;
            }
        }
    }
    let eo = EoFrame {
        width: 160,
        height: 120,
        rgb: (0..160 * 120 * 3).map(|i| (i * 7 % 253) as u8).collect(),
        timestamp_ns: 1_002,
        exposure: None,
    };
    let scan = fuse(&range, eo, &Sensor::new(model), &FuseConfig::default()).unwrap();
    assert!(scan.vertex_count() > 1000 && scan.stretched_count() > 0);
    scan
}

#[test]
fn a_fused_scan_encodes_to_the_same_bytes_by_either_path() {
    let scan = fused_scan();
    check_sendable(&scan).unwrap();
    let world = pose_from_parts([1.0, -2.0, 0.5], [0.1, 0.2, 0.3, 0.9]).unwrap();
    for format in [TextureFormat::Rgb8, TextureFormat::Png, TextureFormat::Jpeg] {
        check_same_bytes(42, &scan, world, format);
    }
}

#[test]
fn checking_a_scan_allocates_nothing_and_encoding_allocates_the_frame_once() {
    let scan = fused_scan();
    let world = Pose::translation(1.0, 2.0, 3.0);
    let (checked, count, _) = allocations(|| check_sendable(&scan));
    assert!(checked.is_ok());
    assert_eq!(count, 0, "check_sendable allocated");

    let texture = texture_of(&scan, TextureFormat::Jpeg);
    let (frame, count, bytes) = allocations(|| {
        WireScanRef::new(9, &scan, world, texture.view())
            .unwrap()
            .encode()
            .unwrap()
    });
    assert_eq!((count, bytes), (1, frame.len()));
    let (frame, count, bytes) = allocations(|| {
        WireScanRef::new(9, &scan, world, TextureRef::rgb8(&scan.texture).unwrap())
            .unwrap()
            .encode()
            .unwrap()
    });
    assert_eq!((count, bytes), (1, frame.len()));

    // The owned path copies the mesh into a `WireScan` before writing the frame.
    let (owned, _, owned_bytes) = allocations(|| owned_frame(9, &scan, world, &texture));
    let mesh = scan.vertex_count() * 25 + scan.triangle_count() * 17;
    assert!(owned_bytes >= owned.len() + mesh, "{owned_bytes} bytes");
}

#[test]
fn header_inconsistencies_are_refused_before_writing() {
    let scan = fused_scan();
    let texture = texture_of(&scan, TextureFormat::Png);
    let world = Pose::identity();
    let mut short = scan.clone();
    short.tex_coords.pop();
    assert!(WireScanRef::new(0, &short, world, texture.view()).is_err());
    let mut bad_noise = scan.clone();
    bad_noise.range_noise.sigma_m = -1.0;
    assert!(WireScanRef::new(0, &bad_noise, world, texture.view()).is_err());
    let mut wrong_raw = texture.view();
    wrong_raw.format = TextureFormat::Rgb8;
    assert!(WireScanRef::new(0, &scan, world, wrong_raw).is_err());
    let mut nan_pose = world;
    nan_pose.translation.vector.x = f64::NAN;
    let view = WireScanRef::new(0, &scan, nan_pose, texture.view()).unwrap();
    assert!(view.encode().is_err());
}

/// Ways to break one rule of the wire.
#[derive(Debug, Clone, Copy)]
enum Break {
    PixelOutsideGrid,
    IndexPastVertices,
    NonFiniteVertex,
    NonFiniteTexCoord,
    AccuracyOutOfRange,
    UnknownFlag,
    NonFiniteCop,
    NegativeNoise,
    NonFiniteLidarPose,
    GridTooWide,
    EmptyTexture,
    InconsistentTexture,
    ShortPerVertexArray,
    ShortPerTriangleArray,
}

impl Break {
    const ALL: [Self; 14] = [
        Self::PixelOutsideGrid,
        Self::IndexPastVertices,
        Self::NonFiniteVertex,
        Self::NonFiniteTexCoord,
        Self::AccuracyOutOfRange,
        Self::UnknownFlag,
        Self::NonFiniteCop,
        Self::NegativeNoise,
        Self::NonFiniteLidarPose,
        Self::GridTooWide,
        Self::EmptyTexture,
        Self::InconsistentTexture,
        Self::ShortPerVertexArray,
        Self::ShortPerTriangleArray,
    ];

    /// Breaks `scan` (false when it has nothing this can break). `k` picks the
    /// element.
    fn apply(self, scan: &mut TexelScan, k: usize) -> bool {
        let (n, m) = (scan.vertex_count(), scan.triangle_count());
        let pixels = scan.grid_width * scan.grid_height;
        match self {
            Self::PixelOutsideGrid if n > 0 => scan.vertex_pixel[k % n] = pixels + k as u32,
            Self::IndexPastVertices if m > 0 => scan.triangles[k % m][k % 3] = n as u32,
            Self::NonFiniteVertex if n > 0 => scan.vertices[k % n][k % 3] = f32::INFINITY,
            Self::NonFiniteTexCoord if n > 0 => scan.tex_coords[k % n][k % 2] = f32::NAN,
            Self::AccuracyOutOfRange if m > 0 => {
                scan.triangle_accuracy[k % m] = [1.5, -0.25, f32::NAN][k % 3];
            }
            Self::UnknownFlag if m > 0 => scan.triangle_flags[k % m].0 |= 4 << (k % 6),
            Self::NonFiniteCop => scan.cop_m[k % 3] = f64::NAN,
            Self::NegativeNoise => scan.range_noise.sigma_per_m = -1e-3,
            Self::NonFiniteLidarPose => scan.scan_from_lidar.translation.vector.y = f64::NAN,
            Self::GridTooWide => scan.grid_width = 1025,
            Self::EmptyTexture => {
                Arc::make_mut(&mut scan.texture).width = 0;
                Arc::make_mut(&mut scan.texture).rgb.clear();
            }
            Self::InconsistentTexture => {
                Arc::make_mut(&mut scan.texture).rgb.pop();
            }
            Self::ShortPerVertexArray if n > 0 => {
                scan.vertex_textured.pop();
            }
            Self::ShortPerTriangleArray if m > 0 => {
                scan.triangle_flags.pop();
            }
            _ => return false,
        }
        true
    }

    /// Whether the frame of a scan broken this way still has the layout the decoder
    /// reads (only its values are wrong), so the decoder can be asked about it.
    fn keeps_layout(self) -> bool {
        !matches!(
            self,
            Self::ShortPerVertexArray | Self::ShortPerTriangleArray
        )
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn random_scans_encode_to_the_same_bytes_by_either_path(
        scan in scan_strategy(),
        id in any::<u64>(),
        world in pose_strategy(),
        format in prop::sample::select(vec![TextureFormat::Rgb8, TextureFormat::Png]),
    ) {
        prop_assert!(check_sendable(&scan).is_ok());
        check_same_bytes(id, &scan, world, format);
    }

    /// `check_sendable` refuses every broken scan, and the decoder refuses the frame
    /// of each one (so the check is neither stricter nor looser than the decoder).
    #[test]
    fn check_sendable_refuses_what_the_decoder_refuses(
        scan in scan_strategy(),
        which in 0..Break::ALL.len(),
        k in 0usize..64,
    ) {
        let decodes = |s: &TexelScan| {
            let frame = reference_frame(&unchecked_wire(0, s, Pose::identity(), raw_texture(&s.texture)));
            decode_frame(&frame, &Limits::FROM_SERVER).map(|m| m.is_some()).unwrap_or(false)
        };
        prop_assert!(check_sendable(&scan).is_ok());
        prop_assert!(decodes(&scan));
        let rule = Break::ALL[which];
        let mut broken = scan;
        if rule.apply(&mut broken, k) {
            prop_assert!(check_sendable(&broken).is_err(), "{rule:?} passed");
            if rule.keeps_layout() {
                prop_assert!(!decodes(&broken), "{rule:?} decoded");
            }
        }
    }
}

#[test]
fn the_geometry_of_a_scan_decodes_without_its_texture() {
    let scan = fused_scan();
    let world = Pose::translation(1.0, 2.0, 3.0);
    let texture = texture_of(&scan, TextureFormat::Jpeg);
    let wire = WireScan::with_texture(9, &scan, world, texture).unwrap();
    let (id, full, pose) = wire.clone().into_scan().unwrap();
    let (geometry_id, geometry, geometry_pose) = wire.into_geometry();
    assert_eq!((geometry_id, geometry_pose), (id, pose));
    assert_eq!((geometry.texture.width, geometry.texture.height), (0, 0));
    let mut untextured = full.clone();
    untextured.texture = geometry.texture.clone();
    assert_eq!(geometry, untextured, "everything but the texture");
    // The coverage signature is geometric: the same from either.
    let config = texel::coverage::CoverageConfig::default();
    assert_eq!(
        texel::coverage::ScanCoverage::of(&geometry, &config),
        texel::coverage::ScanCoverage::of(&full, &config)
    );
}
