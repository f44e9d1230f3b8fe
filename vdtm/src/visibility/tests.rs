#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
use nalgebra::{Isometry3, Point3, Vector3};
use texel::camera::{Distortion, PinholeCamera};

use super::*;

/// A camera at `eye` looking at `target`, image +y along `down`.
fn pose(eye: [f64; 3], target: [f64; 3], down: [f64; 3]) -> Isometry3<f64> {
    Isometry3::face_towards(
        &Point3::from(eye),
        &Point3::from(target),
        &Vector3::from(down),
    )
}

fn view(id: u32, camera: &PinholeCamera, world_from_eo: Isometry3<f64>) -> AcquisitionView<'_> {
    AcquisitionView {
        id,
        world_from_eo,
        camera,
        image: None,
    }
}

/// A `n × n` grid of quads over `[lo, hi]²` in the plane z = `z`, facing +z.
fn grid(n: u32, lo: f32, hi: f32, z: f32) -> SurfaceMesh {
    let mut mesh = SurfaceMesh::empty([0.0; 3]);
    add_grid(&mut mesh, n, lo, hi, z);
    mesh
}

fn add_grid(mesh: &mut SurfaceMesh, n: u32, lo: f32, hi: f32, z: f32) {
    let base = mesh.positions.len() as u32;
    let step = (hi - lo) / n as f32;
    for j in 0..=n {
        for i in 0..=n {
            mesh.positions
                .push([lo + i as f32 * step, lo + j as f32 * step, z]);
            mesh.colours.push([(i * 20) as u8, (j * 20) as u8, 100]);
        }
    }
    let at = |i: u32, j: u32| base + j * (n + 1) + i;
    for j in 0..n {
        for i in 0..n {
            mesh.triangles
                .push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
            mesh.triangles
                .push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
        }
    }
}

fn corners(mesh: &SurfaceMesh, t: usize) -> [Point3<f64>; 3] {
    mesh.triangles[t].map(|v| Point3::from(mesh.world(v as usize).unwrap()))
}

/// The invariants every result keeps.
fn check_consistent(
    input: &SurfaceMesh,
    views: &[AcquisitionView<'_>],
    out: &VisibleMesh,
    stats: &VisibilityStats,
) {
    let n = out.mesh.triangles.len();
    assert_eq!(stats.input_triangles, input.triangles.len());
    assert_eq!(stats.output_triangles, n);
    assert_eq!(n, stats.input_triangles + 3 * stats.subdivided);
    assert_eq!(stats.seen_by_views.iter().sum::<usize>(), n);
    assert_eq!(out.source_triangle.len(), n);
    assert_eq!(out.seen_by.len(), n);
    assert_eq!(out.tiny.len(), n);
    assert_eq!(out.tiny.iter().filter(|t| **t).count(), stats.tiny);
    assert_eq!(out.mesh.positions.len(), out.mesh.colours.len());
    // Bitwise: NaN positions stay as they were.
    let bits =
        |p: &[[f32; 3]]| -> Vec<[u32; 3]> { p.iter().map(|v| v.map(f32::to_bits)).collect() };
    assert_eq!(
        bits(&out.mesh.positions[..input.positions.len()]),
        bits(&input.positions)
    );
    let ids: Vec<u32> = views.iter().map(|v| v.id).collect();
    for (t, seen) in out.seen_by.iter().enumerate() {
        assert!((out.source_triangle[t] as usize) < input.triangles.len());
        assert!(seen.windows(2).all(|w| w[0] < w[1]), "{seen:?}");
        assert!(seen.iter().all(|v| ids.contains(v)), "{seen:?}");
        assert!(
            out.mesh.triangles[t]
                .iter()
                .all(|&v| (v as usize) < out.mesh.positions.len())
        );
    }
    for k in 0..4 {
        let count = out.seen_by.iter().filter(|s| s.len().min(3) == k).count();
        assert_eq!(count, stats.seen_by_views[k]);
    }
}

fn camera(width: u32, height: u32, fov_deg: f64) -> PinholeCamera {
    PinholeCamera::from_vertical_fov(width, height, fov_deg).unwrap()
}

#[test]
fn a_plane_is_seen_from_in_front_and_not_from_behind() {
    let mesh = grid(10, -1.0, 1.0, 0.0);
    let cam = camera(320, 240, 60.0);
    let front = view(3, &cam, pose([0.0, 0.0, 3.0], [0.0; 3], [0.0, -1.0, 0.0]));
    let behind = view(5, &cam, pose([0.0, 0.0, -3.0], [0.0; 3], [0.0, -1.0, 0.0]));
    let views = [front, behind];
    let (out, stats) = visibility(&mesh, &views, &VisibilityConfig::default()).unwrap();
    check_consistent(&mesh, &views, &out, &stats);
    assert_eq!(stats.subdivided, 0);
    assert_eq!(stats.output_triangles, 200);
    assert!(out.seen_by.iter().all(|s| s == &[3]), "{:?}", out.seen_by);
    assert_eq!(stats.seen_by_views, [0, 200, 0, 0]);
    assert_eq!(stats.tiny, 0);
    assert_eq!(stats.depth_map_pixels, 2 * 160 * 120);
}

#[test]
fn the_image_border_splits_the_polygons_it_cuts() {
    let mesh = grid(10, -1.0, 1.0, 0.0);
    // 40 degrees vertical: at 3 m the image spans x in 0.7 ± 1.456 m, so its left
    // border cuts the column of quads over x in [-0.8, -0.6] and y fits inside.
    let cam = camera(320, 240, 40.0);
    let v = view(
        1,
        &cam,
        pose([0.7, 0.0, 3.0], [0.7, 0.0, 0.0], [0.0, -1.0, 0.0]),
    );
    let views = [v];
    let config = VisibilityConfig::default();
    let (out, stats) = visibility(&mesh, &views, &config).unwrap();
    check_consistent(&mesh, &views, &out, &stats);
    assert!(stats.subdivided > 0);
    let (mut cut_seen, mut cut_unseen) = (0, 0);
    for t in 0..out.mesh.triangles.len() {
        let c = corners(&out.mesh, t);
        let min_x = c.iter().map(|p| p.x).fold(f64::INFINITY, f64::min);
        let max_x = c.iter().map(|p| p.x).fold(f64::NEG_INFINITY, f64::max);
        let seen = out.seen_by[t] == [1];
        if seen {
            // None wrongly seen: every corner projects inside the image's margin.
            for p in &c {
                let (pixel, _) = v.project(p).unwrap();
                assert!(
                    v.inside(&pixel, config.border_margin_px),
                    "triangle {t} seen with corner at {pixel:?}"
                );
            }
        }
        if min_x >= -0.6 - 1e-6 {
            assert!(seen, "triangle {t} wholly inside is not seen");
            assert!(!out.tiny[t]);
        } else if max_x <= -0.8 + 1e-6 {
            assert!(
                out.seen_by[t].is_empty(),
                "triangle {t} wholly outside is seen"
            );
        } else {
            let src = out.source_triangle[t] as usize;
            assert_ne!(
                out.mesh.triangles[t], mesh.triangles[src],
                "a cut triangle was not split"
            );
            if seen {
                cut_seen += 1;
            } else {
                cut_unseen += 1;
            }
        }
    }
    assert!(cut_seen > 0 && cut_unseen > 0, "{cut_seen} {cut_unseen}");
    // Pieces at the limit that straddle the border are the tiny ones.
    assert!(stats.tiny > 0);
    assert!(
        out.tiny
            .iter()
            .zip(&out.seen_by)
            .all(|(tiny, s)| !tiny || s.is_empty())
    );
}

#[test]
fn no_subdivision_leaves_cut_polygons_tiny() {
    let mesh = grid(10, -1.0, 1.0, 0.0);
    let cam = camera(320, 240, 40.0);
    let views = [view(
        1,
        &cam,
        pose([0.7, 0.0, 3.0], [0.7, 0.0, 0.0], [0.0, -1.0, 0.0]),
    )];
    for config in [
        VisibilityConfig {
            max_subdivision: 0,
            ..VisibilityConfig::default()
        },
        VisibilityConfig {
            min_area_m2: 1.0,
            ..VisibilityConfig::default()
        },
    ] {
        let (out, stats) = visibility(&mesh, &views, &config).unwrap();
        check_consistent(&mesh, &views, &out, &stats);
        assert_eq!(stats.subdivided, 0);
        // The column of 10 quads the border cuts: 20 triangles.
        assert_eq!(stats.tiny, 20);
        assert_eq!(out.mesh, mesh);
    }
}

/// A 4 m plane and a 0.4 m plate 1.5 m above its centre, both facing +z; camera A
/// straight above at 4 m, camera B off to the side, whose view of the plate's
/// shadow region is clear.
#[test]
fn an_occluder_hides_what_is_behind_it_from_one_view_only() {
    let mut mesh = grid(20, -2.0, 2.0, 0.0);
    let plane_triangles = mesh.triangles.len();
    add_grid(&mut mesh, 1, -0.2, 0.2, 1.5);
    let cam = camera(640, 480, 70.0);
    let a = view(0, &cam, pose([0.0, 0.0, 4.0], [0.0; 3], [0.0, -1.0, 0.0]));
    let b = view(1, &cam, pose([3.0, 0.0, 3.0], [0.0; 3], [0.0, 0.0, -1.0]));
    let views = [a, b];
    let (out, stats) = visibility(&mesh, &views, &VisibilityConfig::default()).unwrap();
    check_consistent(&mesh, &views, &out, &stats);
    // From A the plate's shadow on the plane is [-0.32, 0.32]²; from B it falls off
    // the plane (x in [-3.4, -2.6]).
    let (mut shadowed, mut clear) = (0, 0);
    for t in 0..out.mesh.triangles.len() {
        if out.source_triangle[t] as usize >= plane_triangles {
            assert_eq!(out.seen_by[t], [0, 1], "the plate is seen by both");
            continue;
        }
        let c = corners(&out.mesh, t);
        let extent = |f: fn(&Point3<f64>) -> f64| {
            let lo = c.iter().map(f).fold(f64::INFINITY, f64::min);
            let hi = c.iter().map(f).fold(f64::NEG_INFINITY, f64::max);
            (lo, hi)
        };
        let ((x0, x1), (y0, y1)) = (extent(|p| p.x), extent(|p| p.y));
        // Inside the shadow by a margin of about two depth-map pixels (0.02 m at
        // A's scale), or clear of it by as much.
        let inner = 0.32 - 0.05;
        let outer = 0.32 + 0.05;
        if x0 >= -inner && x1 <= inner && y0 >= -inner && y1 <= inner {
            shadowed += 1;
            assert_eq!(out.seen_by[t], [1], "shadowed triangle {t}: {c:?}");
        } else if x1 <= -outer || x0 >= outer || y1 <= -outer || y0 >= outer {
            clear += 1;
            assert!(
                out.seen_by[t].contains(&0),
                "triangle {t} clear of the shadow: {c:?}"
            );
        }
        if out.seen_by[t].contains(&0) {
            // Never seen by A where the plate is in the way: no corner in the shadow
            // by more than the neighbourhood's slack.
            let slack = 0.32 - 0.03;
            assert!(
                !c.iter().any(|p| p.x.abs() < slack && p.y.abs() < slack),
                "triangle {t} seen through the plate: {c:?}"
            );
        }
    }
    assert!(shadowed >= 8 && clear > 600, "{shadowed} {clear}");
    assert!(stats.subdivided > 0);
}

#[test]
fn degenerate_and_non_finite_triangles_are_seen_by_none() {
    let mut mesh = grid(1, -1.0, 1.0, 0.0);
    let n = mesh.positions.len() as u32;
    mesh.positions.extend([
        [0.0, 0.0, 0.1],
        [0.5, 0.0, 0.1],
        [1.0, 0.0, 0.1],
        [f32::NAN, 0.0, 0.2],
        [f32::INFINITY, 1.0, 0.2],
    ]);
    mesh.colours.extend([[0; 3]; 5]);
    mesh.triangles.extend([
        [n, n + 1, n + 2],     // collinear
        [n, n, n],             // one point
        [n + 3, n, n + 1],     // NaN corner
        [n + 4, n + 1, n],     // infinite corner
        [n + 3, n + 4, n + 3], // nothing finite
    ]);
    let cam = camera(320, 240, 60.0);
    let views = [view(
        7,
        &cam,
        pose([0.0, 0.0, 3.0], [0.0; 3], [0.0, -1.0, 0.0]),
    )];
    let (out, stats) = visibility(&mesh, &views, &VisibilityConfig::default()).unwrap();
    check_consistent(&mesh, &views, &out, &stats);
    assert_eq!(stats.degenerate, 5);
    assert_eq!(out.seen_by[..2], [vec![7], vec![7]]);
    assert!(out.seen_by[2..].iter().all(Vec::is_empty));
    assert!(out.tiny.iter().all(|t| !t));
    // A view whose pose is not finite sees nothing and breaks nothing.
    let mut bad = pose([0.0, 0.0, 3.0], [0.0; 3], [0.0, -1.0, 0.0]);
    bad.translation.vector.x = f64::NAN;
    let views = [view(2, &cam, bad)];
    let (out, stats) = visibility(&mesh, &views, &VisibilityConfig::default()).unwrap();
    check_consistent(&mesh, &views, &out, &stats);
    assert!(out.seen_by.iter().all(Vec::is_empty));
}

#[test]
fn bad_input_is_an_error() {
    let mesh = grid(2, -1.0, 1.0, 0.0);
    let cam = camera(320, 240, 60.0);
    let eye = pose([0.0, 0.0, 3.0], [0.0; 3], [0.0, -1.0, 0.0]);
    let config = VisibilityConfig::default();

    let mut broken = mesh.clone();
    broken.triangles.push([0, 1, 99]);
    assert!(matches!(
        visibility(&broken, &[view(0, &cam, eye)], &config),
        Err(VisibilityError::IndexOutOfRange { vertex: 99, .. })
    ));
    let mut broken = mesh.clone();
    broken.colours.pop();
    assert!(matches!(
        visibility(&broken, &[view(0, &cam, eye)], &config),
        Err(VisibilityError::ColourCount { .. })
    ));

    let empty = PinholeCamera {
        width: 0,
        height: 240,
        fx: 100.0,
        fy: 100.0,
        cx: 0.0,
        cy: 120.0,
        skew: 0.0,
        distortion: Distortion::None,
    };
    assert_eq!(
        visibility(&mesh, &[view(4, &empty, eye)], &config),
        Err(VisibilityError::EmptyImage {
            view: 4,
            width: 0,
            height: 240
        })
    );
    let huge = PinholeCamera {
        width: 16_384,
        height: 16_384,
        ..empty
    };
    let fine = VisibilityConfig {
        depth_map_scale: 2.0,
        ..config
    };
    assert!(matches!(
        visibility(&mesh, &[view(4, &huge, eye)], &fine),
        Err(VisibilityError::DepthMapTooLarge { view: 4, .. })
    ));

    for bad in [
        VisibilityConfig {
            depth_map_scale: 0.0,
            ..config
        },
        VisibilityConfig {
            depth_map_scale: f64::NAN,
            ..config
        },
        VisibilityConfig {
            depth_tolerance_m: -1.0,
            ..config
        },
        VisibilityConfig {
            border_margin_px: f64::INFINITY,
            ..config
        },
        VisibilityConfig {
            max_subdivision: MAX_SUBDIVISION + 1,
            ..config
        },
        VisibilityConfig {
            min_area_m2: f64::NAN,
            ..config
        },
    ] {
        assert!(matches!(
            visibility(&mesh, &[view(0, &cam, eye)], &bad),
            Err(VisibilityError::Config(_))
        ));
    }
}

#[test]
fn no_views_and_no_triangles() {
    let mesh = grid(3, -1.0, 1.0, 0.0);
    let (out, stats) = visibility(&mesh, &[], &VisibilityConfig::default()).unwrap();
    check_consistent(&mesh, &[], &out, &stats);
    assert_eq!(stats.seen_by_views, [18, 0, 0, 0]);
    let empty = SurfaceMesh::empty([1.0, 2.0, 3.0]);
    let cam = camera(64, 48, 60.0);
    let views = [view(
        0,
        &cam,
        pose([0.0, 0.0, 3.0], [0.0; 3], [0.0, -1.0, 0.0]),
    )];
    let (out, stats) = visibility(&empty, &views, &VisibilityConfig::default()).unwrap();
    assert_eq!(out.mesh, empty);
    assert_eq!(stats.output_triangles, 0);
}

#[test]
fn a_polygon_passing_behind_the_camera_still_occludes() {
    // A large slanted roof between a camera at z = 3 looking down and a plane at
    // z = 0: it rises from z = 1 to z = 4, so its far corner lies behind the camera
    // (above it); its clipped part still hides the plane.
    let mut mesh = grid(4, -1.0, 1.0, 0.0);
    let plane_triangles = mesh.triangles.len();
    let n = mesh.positions.len() as u32;
    mesh.positions
        .extend([[-50.0, -50.0, 1.0], [50.0, -50.0, 1.0], [0.0, 50.0, 4.0]]);
    mesh.colours.extend([[0; 3]; 3]);
    mesh.triangles.push([n, n + 1, n + 2]);
    let cam = camera(320, 240, 60.0);
    let views = [view(
        0,
        &cam,
        pose([0.0, 0.0, 3.0], [0.0; 3], [0.0, -1.0, 0.0]),
    )];
    let (out, stats) = visibility(&mesh, &views, &VisibilityConfig::default()).unwrap();
    check_consistent(&mesh, &views, &out, &stats);
    for t in 0..out.mesh.triangles.len() {
        if (out.source_triangle[t] as usize) < plane_triangles {
            assert!(
                out.seen_by[t].is_empty(),
                "triangle {t} seen through the wall"
            );
        }
    }
}

#[test]
fn a_corner_just_outside_the_image_is_not_seen_wholly() {
    // One large triangle in z = 0 below a camera looking straight down: its right
    // corner projects 0.7 px beyond the margin, its sample (pulled 1 % towards the
    // centroid, about 1 px) inside. The exact corner decides: seen only in part.
    let cam = camera(320, 240, 60.0);
    let eye = pose([0.0, 0.0, 3.0], [0.0; 3], [0.0, -1.0, 0.0]);
    let on_ground = |u: f64, v: f64| {
        // Camera x is world x, camera y world -y, at depth 3.
        [
            ((u - cam.cx) * 3.0 / cam.fx) as f32,
            (-(v - cam.cy) * 3.0 / cam.fy) as f32,
            0.0,
        ]
    };
    let mut mesh = SurfaceMesh::empty([0.0; 3]);
    mesh.positions = vec![
        on_ground(160.0, 200.0),
        on_ground(319.2, 120.0),
        on_ground(160.0, 40.0),
    ];
    mesh.colours = vec![[0; 3]; 3];
    mesh.triangles = vec![[0, 1, 2]];
    let views = [view(0, &cam, eye)];
    let c = corners(&mesh, 0);
    assert!(
        (c[1] - c[0]).cross(&(c[2] - c[0])).z > 0.0,
        "faces the camera"
    );
    let config = VisibilityConfig {
        max_subdivision: 0,
        ..VisibilityConfig::default()
    };
    let (out, stats) = visibility(&mesh, &views, &config).unwrap();
    check_consistent(&mesh, &views, &out, &stats);
    assert_eq!(out.seen_by, [Vec::<u32>::new()]);
    assert_eq!(out.tiny, [true]);
    // Moved inside by 2 px, it is seen.
    mesh.positions[1] = on_ground(317.2, 120.0);
    let (out, _) = visibility(&mesh, &views, &config).unwrap();
    assert_eq!(out.seen_by, [vec![0]]);
}
