//! The whole preprocessing on a small scene with known geometry: a box on the ground,
//! a plate under the ground no view can see, two views from one side. Checked against
//! an independent ray test of the true geometry (no polygon counts as seen through the
//! box or the ground), the holes' colours (from their neighbours, the unreachable
//! plate grey), and the per-frame blends.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use nalgebra::{Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use texel::Pose;
use texel::camera::{Distortion, PinholeCamera};
use texel::frames::EoFrame;
use texel_surface::SurfaceMesh;
use texel_vdtm::{
    AcquisitionView, Texturing, VdtmConfig, VdtmModel, fill_holes, triangle_colours, visibility,
};

/// Adds the quad `a b c d` (counter-clockwise seen from its front) as two triangles,
/// sharing the vertices already at its corners (as a merged surface does).
fn quad(mesh: &mut SurfaceMesh, corners: [[f64; 3]; 4]) {
    let index: Vec<u32> = corners
        .iter()
        .map(|c| {
            let p = c.map(|v| v as f32);
            match mesh.positions.iter().position(|q| *q == p) {
                Some(i) => i as u32,
                None => {
                    mesh.positions.push(p);
                    mesh.colours.push([0, 0, 0]);
                    (mesh.positions.len() - 1) as u32
                }
            }
        })
        .collect();
    mesh.triangles.push([index[0], index[1], index[2]]);
    mesh.triangles.push([index[0], index[2], index[3]]);
}

/// A ground grid at height `z` over `[-half, half]²`, `cells` a side, facing up.
fn ground(mesh: &mut SurfaceMesh, z: f64, half: f64, cells: usize) {
    let step = 2.0 * half / cells as f64;
    for j in 0..cells {
        for i in 0..cells {
            let (x0, y0) = (-half + i as f64 * step, -half + j as f64 * step);
            let (x1, y1) = (x0 + step, y0 + step);
            quad(mesh, [[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]]);
        }
    }
}

/// The box `[-0.5, 0.5]² x [0, 1]`: its top and four sides, facing out.
fn unit_box(mesh: &mut SurfaceMesh) {
    let (l, h) = (-0.5, 0.5);
    quad(mesh, [[l, l, 1.0], [h, l, 1.0], [h, h, 1.0], [l, h, 1.0]]);
    quad(mesh, [[h, l, 0.0], [h, h, 0.0], [h, h, 1.0], [h, l, 1.0]]);
    quad(mesh, [[l, h, 0.0], [l, l, 0.0], [l, l, 1.0], [l, h, 1.0]]);
    quad(mesh, [[h, h, 0.0], [l, h, 0.0], [l, h, 1.0], [h, h, 1.0]]);
    quad(mesh, [[l, l, 0.0], [h, l, 0.0], [h, l, 1.0], [l, l, 1.0]]);
}

fn scene() -> SurfaceMesh {
    let mut mesh = SurfaceMesh::empty([0.0; 3]);
    ground(&mut mesh, 0.0, 4.0, 16);
    unit_box(&mut mesh);
    ground(&mut mesh, -0.5, 1.0, 2);
    mesh
}

fn camera() -> PinholeCamera {
    PinholeCamera {
        width: 160,
        height: 120,
        fx: 90.0,
        fy: 90.0,
        cx: 79.5,
        cy: 59.5,
        skew: 0.0,
        distortion: Distortion::None,
    }
}

/// The EO optical frame (+x right, +y down, +z forward) at `eye` looking at `target`.
fn looking(eye: [f64; 3], target: [f64; 3]) -> Pose {
    let (eye, target) = (Vector3::from(eye), Vector3::from(target));
    let z = (target - eye).normalize();
    let x = z.cross(&Vector3::z()).normalize();
    let y = z.cross(&x);
    let rotation = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Pose::from_parts(
        Translation3::from(eye),
        UnitQuaternion::from_rotation_matrix(&rotation),
    )
}

fn image(rgb: [u8; 3]) -> EoFrame {
    EoFrame {
        width: 160,
        height: 120,
        rgb: rgb.repeat(160 * 120),
        timestamp_ns: 0,
        exposure: None,
    }
}

/// Whether the open segment from `p` to `q` passes through the box (shrunk by a
/// millimetre so a face's own polygons do not count) or crosses the ground plane.
fn blocked(p: Point3<f64>, q: Point3<f64>) -> bool {
    let d = q - p;
    let (mut t0, mut t1) = (1e-6, 1.0 - 1e-6);
    for a in 0..3 {
        let (lo, hi) = if a == 2 {
            (0.001, 0.999)
        } else {
            (-0.499, 0.499)
        };
        if d[a].abs() < 1e-12 {
            if p[a] < lo || p[a] > hi {
                t1 = -1.0;
            }
            continue;
        }
        let (ta, tb) = ((lo - p[a]) / d[a], (hi - p[a]) / d[a]);
        t0 = f64::max(t0, ta.min(tb));
        t1 = f64::min(t1, ta.max(tb));
    }
    let through_box = t0 < t1;
    let crosses_ground = p.z < -0.1 && q.z > 0.0;
    through_box || crosses_ground
}

#[test]
fn the_model_of_a_box_on_the_ground_agrees_with_the_true_geometry() {
    let mesh = scene();
    let cam = camera();
    let (red, green) = (image([255, 0, 0]), image([0, 255, 0]));
    let views = [
        AcquisitionView {
            id: 10,
            world_from_eo: looking([6.0, 1.5, 4.0], [0.0, 0.0, 0.5]),
            camera: &cam,
            image: Some(&red),
        },
        AcquisitionView {
            id: 20,
            world_from_eo: looking([6.0, -1.5, 4.0], [0.0, 0.0, 0.5]),
            camera: &cam,
            image: Some(&green),
        },
    ];
    let config = VdtmConfig::default();
    let model = VdtmModel::build(&mesh, &views, &config).unwrap();
    // Sampling only the polygons next to holes fills them as sampling every one does.
    let (visible, _) = visibility(&mesh, &views, &config.visibility).unwrap();
    let all = triangle_colours(&visible.mesh, &visible.seen_by, &views, &config.hole_fill);
    let full = fill_holes(&visible.mesh, &all, &config.hole_fill).unwrap();
    for (t, how) in model.texturing.iter().enumerate() {
        if let Texturing::Hole { corners } = how {
            assert_eq!(Some(*corners), full.corner_colours[t], "polygon {t}");
        }
    }
    let n = model.mesh.triangle_count();
    let s = model.stats;
    assert_eq!(s.holes + s.single + s.mapped, n);
    assert_eq!(model.texturing.len(), n);
    assert!(s.mapped > 0 && s.single > 0 && s.holes > 0, "{s:?}");
    let corners = |t: usize| {
        model.mesh.triangles[t].map(|v| Point3::from(model.mesh.world(v as usize).unwrap()))
    };
    let mut seen_checked = 0;
    for t in 0..n {
        let [a, b, c] = corners(t);
        let centroid = Point3::from((a.coords + b.coords + c.coords) / 3.0);
        let seen = &model.seen_by[t];
        match &model.texturing[t] {
            Texturing::Hole { corners } => {
                assert!(seen.is_empty());
                // A hole's colours come from its neighbours (red, green or their mean:
                // never blue) or, under the ground, the grey fallback.
                for c in corners {
                    assert!(c.iter().all(|v| v.is_finite() && (0.0..=1.0).contains(v)));
                    if centroid.z < -0.1 {
                        assert_eq!(*c, [0.5; 3], "the plate under the ground");
                    } else {
                        assert_eq!(c[2], 0.0, "a hole coloured from nowhere: {c:?}");
                    }
                }
            }
            Texturing::Single(v) => assert_eq!(seen, &vec![*v]),
            Texturing::Mapped(_) => assert!(seen.len() >= 2),
        }
        // No polygon is seen through the box or the ground: every corner of a polygon
        // a view sees has a clear line to that view.
        for id in seen {
            let view = views.iter().find(|v| v.id == *id).unwrap();
            for p in [a, b, c, centroid] {
                let towards = p + (view.centre() - p) * 1e-4;
                assert!(
                    !blocked(towards, view.centre()),
                    "polygon {t} at {centroid:?} seen by {id} through the geometry"
                );
            }
            seen_checked += 1;
        }
        if centroid.z < -0.1 {
            assert!(matches!(model.texturing[t], Texturing::Hole { .. }));
        }
    }
    assert!(seen_checked > 100);
    // The ground right behind the box, hidden from both views, is a hole; the ground
    // in front of it is seen by both and mapped.
    let at = |x: f64, y: f64| {
        (0..n)
            .find(|t| {
                let [a, b, c] = corners(*t);
                let m = (a.coords + b.coords + c.coords) / 3.0;
                m.z.abs() < 1e-9 && (m.x - x).abs() < 0.2 && (m.y - y).abs() < 0.2
            })
            .unwrap()
    };
    assert!(matches!(
        model.texturing[at(-1.0, 0.0)],
        Texturing::Hole { .. }
    ));
    assert!(matches!(
        model.texturing[at(2.0, 0.0)],
        Texturing::Mapped(_)
    ));
    // §8: from each view's own place, that view leads the blend of a polygon both
    // see; from anywhere, the weights are a partition of one.
    let front = at(2.0, 0.0);
    for view in &views {
        let blend = model.blend(front, &view.centre()).unwrap();
        assert_eq!(blend.iter().next().unwrap().0, view.id, "{blend:?}");
    }
    for eye in [[0.0, 0.0, 10.0], [-6.0, 0.0, 1.0], [2.0, 0.0, -3.0]] {
        for t in 0..n {
            if let Some(b) = model.blend(t, &Point3::from(eye)) {
                let total: f64 = b.iter().map(|(_, w)| w).sum();
                assert!((total - 1.0).abs() < 1e-12);
                assert!(
                    b.iter()
                        .all(|(v, w)| [10, 20].contains(&v) && (0.0..=1.0).contains(&w))
                );
            }
        }
    }
}
