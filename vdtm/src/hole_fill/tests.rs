#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
use std::collections::VecDeque;

use nalgebra::Isometry3;
use texel::camera::{Distortion, PinholeCamera};

use super::*;

const RED: [f32; 3] = [1.0, 0.0, 0.0];
const GREEN: [f32; 3] = [0.0, 1.0, 0.0];
const BLUE: [f32; 3] = [0.0, 0.0, 1.0];

fn mesh(positions: Vec<[f32; 3]>, triangles: Vec<[u32; 3]>) -> SurfaceMesh {
    SurfaceMesh {
        origin_m: [100.0, 200.0, 0.0],
        colours: vec![[0; 3]; positions.len()],
        positions,
        triangles,
    }
}

/// A strip along x of `cells` unit squares, two triangles each: bottom vertices
/// `2i`, top vertices `2i + 1` at x = i; triangle order follows x.
fn strip(cells: u32) -> SurfaceMesh {
    let mut positions = Vec::new();
    for i in 0..=cells {
        positions.push([i as f32, 0.0, 0.0]);
        positions.push([i as f32, 1.0, 0.0]);
    }
    let mut triangles = Vec::new();
    for i in 0..cells {
        let (b0, t0, b1, t1) = (2 * i, 2 * i + 1, 2 * i + 2, 2 * i + 3);
        triangles.push([b0, b1, t0]);
        triangles.push([b1, t1, t0]);
    }
    mesh(positions, triangles)
}

/// A grid of `cols × rows` unit squares over x ∈ [x0, x0 + cols], y ∈ [y0, y0 + rows]
/// on z = 0, two triangles each (cell (i, j) holds triangles 2(j·cols + i) and +1).
fn grid(cols: u32, rows: u32, x0: f32, y0: f32) -> SurfaceMesh {
    let mut positions = Vec::new();
    for j in 0..=rows {
        for i in 0..=cols {
            positions.push([x0 + i as f32, y0 + j as f32, 0.0]);
        }
    }
    let v = |i: u32, j: u32| j * (cols + 1) + i;
    let mut triangles = Vec::new();
    for j in 0..rows {
        for i in 0..cols {
            triangles.push([v(i, j), v(i + 1, j), v(i + 1, j + 1)]);
            triangles.push([v(i, j), v(i + 1, j + 1), v(i, j + 1)]);
        }
    }
    mesh(positions, triangles)
}

/// Rounds by breadth-first search over triangles sharing a vertex, from the coloured.
fn bfs_rounds(mesh: &SurfaceMesh, colours: &[Option<[f32; 3]>]) -> Vec<u32> {
    let n = mesh.triangles.len();
    let mut round = vec![u32::MAX; n];
    let mut queue = VecDeque::new();
    for t in 0..n {
        if colours[t].is_some() {
            round[t] = 0;
            queue.push_back(t);
        }
    }
    while let Some(t) = queue.pop_front() {
        for u in 0..n {
            let shares = mesh.triangles[u]
                .iter()
                .any(|v| mesh.triangles[t].contains(v));
            if shares && round[u] == u32::MAX {
                round[u] = round[t] + 1;
                queue.push_back(u);
            }
        }
    }
    round
}

fn all_finite(fill: &HoleFill) -> bool {
    fill.corner_colours
        .iter()
        .flatten()
        .flatten()
        .flatten()
        .all(|c| c.is_finite())
}

#[test]
fn a_strip_fills_from_both_ends_in_rounds_by_distance() {
    let m = strip(10);
    let n = m.triangles.len();
    let mut colours = vec![None; n];
    colours[0] = Some(RED);
    colours[n - 1] = Some(BLUE);
    let fill = fill_holes(&m, &colours, &HoleFillConfig::default()).unwrap();

    assert_eq!(fill.round, bfs_rounds(&m, &colours));
    assert!(
        fill.round
            .iter()
            .skip(1)
            .take(n - 2)
            .all(|&r| r > 0 && r < u32::MAX)
    );
    assert!(fill.round[n / 2] >= 4, "{:?}", fill.round);
    assert_eq!(fill.corner_colours[0], None);
    assert_eq!(fill.corner_colours[n - 1], None);
    assert_eq!(
        fill.stats,
        HoleFillStats {
            coloured: 2,
            filled: n - 2,
            rounds: *fill.round.iter().max().unwrap(),
            fallback: 0,
            hit_round_limit: false,
        }
    );
    let x_mid = 5.0;
    for t in 1..n - 1 {
        let corners = fill.corner_colours[t].unwrap();
        assert!(
            corners.iter().all(|c| *c == RED || *c == BLUE),
            "{t}: {corners:?}"
        );
        let xs = m.triangles[t].map(|v| m.positions[v as usize][0]);
        let centroid_x = xs.iter().sum::<f32>() / 3.0;
        // The corner nearest the red end is red on the red half, and the corner
        // nearest the blue end blue on the blue half.
        let (lowest, highest) = (
            (0..3).min_by(|&a, &b| xs[a].total_cmp(&xs[b])).unwrap(),
            (0..3).max_by(|&a, &b| xs[a].total_cmp(&xs[b])).unwrap(),
        );
        if centroid_x < x_mid {
            assert_eq!(corners[lowest], RED, "{t}: {corners:?}");
        } else {
            assert_eq!(corners[highest], BLUE, "{t}: {corners:?}");
        }
    }
    // Next to each end, wholly that end's colour.
    assert_eq!(fill.corner_colours[1], Some([RED; 3]));
    assert_eq!(fill.corner_colours[n - 2], Some([BLUE; 3]));
    assert!(all_finite(&fill));
}

#[test]
fn a_hole_surrounded_by_one_colour_takes_it_exactly() {
    // 5 × 5 cells, the middle 3 × 3 cells (18 triangles, two rings deep) unseen.
    let m = grid(5, 5, 0.0, 0.0);
    let colour = [0.25, 0.5, 0.75];
    let colours: Vec<_> = (0..m.triangles.len())
        .map(|t| {
            let cell = t as u32 / 2;
            let (i, j) = (cell % 5, cell / 5);
            let inside = (1..4).contains(&i) && (1..4).contains(&j);
            (!inside).then_some(colour)
        })
        .collect();
    let fill = fill_holes(&m, &colours, &HoleFillConfig::default()).unwrap();
    assert_eq!(fill.stats.filled, 18);
    assert_eq!(fill.stats.rounds, 2);
    for (t, c) in colours.iter().enumerate() {
        match c {
            Some(_) => assert_eq!(fill.corner_colours[t], None),
            None => assert_eq!(fill.corner_colours[t], Some([colour; 3])),
        }
    }
    assert_eq!(fill.round, bfs_rounds(&m, &colours));
}

#[test]
fn a_component_no_view_saw_gets_the_fallback() {
    let mut m = strip(3);
    let base = m.positions.len() as u32;
    m.positions
        .extend([[10.0, 0.0, 0.0], [11.0, 0.0, 0.0], [10.0, 1.0, 0.0]]);
    m.triangles.push([base, base + 1, base + 2]);
    let mut colours = vec![None; m.triangles.len()];
    colours[0] = Some(GREEN);
    let config = HoleFillConfig {
        fallback_colour: [0.1, 0.2, 0.3],
        ..HoleFillConfig::default()
    };
    let fill = fill_holes(&m, &colours, &config).unwrap();
    let last = m.triangles.len() - 1;
    assert_eq!(fill.round[last], u32::MAX);
    assert_eq!(fill.corner_colours[last], Some([[0.1, 0.2, 0.3]; 3]));
    assert_eq!(fill.stats.fallback, 1);
    assert!(!fill.stats.hit_round_limit);
    for t in 1..last {
        assert_eq!(fill.corner_colours[t], Some([GREEN; 3]));
        assert!(fill.round[t] > 0 && fill.round[t] < u32::MAX);
    }
    // Nothing coloured at all: everything falls back.
    let none = fill_holes(&m, &vec![None; m.triangles.len()], &config).unwrap();
    assert!(none.round.iter().all(|&r| r == u32::MAX));
    assert_eq!(none.stats.fallback, m.triangles.len());
    assert_eq!(none.stats.rounds, 0);
}

#[test]
fn the_round_limit_leaves_the_far_holes_to_the_fallback() {
    let m = strip(10);
    let n = m.triangles.len();
    let mut colours = vec![None; n];
    colours[0] = Some(RED);
    let config = HoleFillConfig {
        max_rounds: 2,
        ..HoleFillConfig::default()
    };
    let fill = fill_holes(&m, &colours, &config).unwrap();
    let expected = bfs_rounds(&m, &colours);
    assert!(fill.stats.hit_round_limit);
    assert_eq!(fill.stats.rounds, 2);
    for (t, &want) in expected.iter().enumerate() {
        if want <= 2 {
            assert_eq!(fill.round[t], want);
        } else {
            assert_eq!(fill.round[t], u32::MAX);
            assert_eq!(fill.corner_colours[t], Some([DEFAULT_FALLBACK_COLOUR; 3]));
        }
    }
    let zero = HoleFillConfig {
        max_rounds: 0,
        ..HoleFillConfig::default()
    };
    let fill = fill_holes(&m, &colours, &zero).unwrap();
    assert_eq!(fill.stats.fallback, n - 1);
}

/// A small deterministic permutation (a linear congruential shuffle).
fn permutation(n: usize, seed: u64) -> Vec<usize> {
    let mut order: Vec<usize> = (0..n).collect();
    let mut state = seed;
    for i in (1..n).rev() {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        let j = (state >> 33) as usize % (i + 1);
        order.swap(i, j);
    }
    order
}

#[test]
fn the_result_does_not_depend_on_triangle_order() {
    // A regular grid (many equal distances) with several colours and scattered holes.
    let m = grid(7, 6, 0.0, 0.0);
    let n = m.triangles.len();
    let palette = [RED, GREEN, BLUE, [0.5, 0.5, 0.0]];
    let colours: Vec<_> = (0..n)
        .map(|t| (t % 5 == 0 || t % 7 == 3).then_some(palette[t % 4]))
        .collect();
    let base = fill_holes(&m, &colours, &HoleFillConfig::default()).unwrap();
    assert!(base.stats.filled > 0);
    for seed in [1, 2, 3, 42] {
        let order = permutation(n, seed);
        let mut shuffled = m.clone();
        shuffled.triangles = order.iter().map(|&t| m.triangles[t]).collect();
        let shuffled_colours: Vec<_> = order.iter().map(|&t| colours[t]).collect();
        let fill = fill_holes(&shuffled, &shuffled_colours, &HoleFillConfig::default()).unwrap();
        for (k, &t) in order.iter().enumerate() {
            assert_eq!(
                fill.corner_colours[k], base.corner_colours[t],
                "seed {seed}"
            );
            assert_eq!(fill.round[k], base.round[t], "seed {seed}");
        }
        assert_eq!(fill.stats, base.stats);
    }
}

#[test]
fn a_mixed_neighbourhood_gives_each_corner_its_nearest_colour() {
    // Three cells in a row: left coloured red, right blue, the middle two holes. The
    // middle cell's left corners touch only red-side triangles, its right corners
    // only blue-side ones.
    let m = grid(3, 1, 0.0, 0.0);
    let colours = vec![Some(RED), Some(RED), None, None, Some(BLUE), Some(BLUE)];
    let fill = fill_holes(&m, &colours, &HoleFillConfig::default()).unwrap();
    for t in [2, 3] {
        let corners = fill.corner_colours[t].unwrap();
        for (k, &v) in m.triangles[t].iter().enumerate() {
            let x = m.positions[v as usize][0];
            let want = if x < 1.5 { RED } else { BLUE };
            assert_eq!(corners[k], want, "triangle {t} corner {k}");
        }
    }
}

#[test]
fn degenerate_input_is_refused_or_survived() {
    // Empty mesh: empty output.
    let empty = mesh(Vec::new(), Vec::new());
    let fill = fill_holes(&empty, &[], &HoleFillConfig::default()).unwrap();
    assert!(fill.corner_colours.is_empty() && fill.round.is_empty());
    assert_eq!(fill.stats, HoleFillStats::default());
    assert!(triangle_colours(&empty, &[], &[], &HoleFillConfig::default()).is_empty());

    // Colour count mismatch.
    let m = strip(2);
    assert_eq!(
        fill_holes(&m, &[Some(RED)], &HoleFillConfig::default()),
        Err(HoleFillError::ColourCount {
            colours: 1,
            triangles: 4
        })
    );

    // Index out of range: an error for filling, no colour (and no panic) for sampling.
    let mut bad = strip(2);
    bad.triangles[2] = [0, 1, 99];
    assert_eq!(
        fill_holes(
            &bad,
            &[Some(RED), None, None, None],
            &HoleFillConfig::default()
        ),
        Err(HoleFillError::VertexIndex {
            triangle: 2,
            vertex: 99,
            vertices: 6
        })
    );
    let sampled = triangle_colours(&bad, &vec![vec![1]; 4], &[], &HoleFillConfig::default());
    assert_eq!(sampled, vec![None; 4]);

    // A fallback colour not finite.
    let config = HoleFillConfig {
        fallback_colour: [f32::NAN, 0.0, 0.0],
        ..HoleFillConfig::default()
    };
    assert!(matches!(
        fill_holes(&m, &[None; 4], &config),
        Err(HoleFillError::NonFiniteFallback(_))
    ));

    // NaN positions and NaN colours: filled, never NaN.
    let mut nan = strip(6);
    nan.positions[5] = [f32::NAN, 0.0, 0.0];
    nan.positions[8] = [f32::INFINITY, f32::NAN, 0.0];
    let n = nan.triangles.len();
    let mut colours = vec![None; n];
    colours[0] = Some(RED);
    colours[n - 1] = Some(BLUE);
    colours[3] = Some([f32::NAN, 0.0, 0.0]);
    let fill = fill_holes(&nan, &colours, &HoleFillConfig::default()).unwrap();
    assert!(all_finite(&fill));
    assert_eq!(fill.stats.fallback, 0);
    assert_eq!(fill.stats.coloured, 2);
    assert!(fill.corner_colours[3].is_some(), "a NaN colour is a hole");
    for c in fill.corner_colours.iter().flatten().flatten() {
        assert!(*c == RED || *c == BLUE, "{c:?}");
    }
}

// --- step 2: sampling the views ---

const W: u32 = 64;
const H: u32 = 48;

fn camera() -> PinholeCamera {
    PinholeCamera {
        width: W,
        height: H,
        fx: 50.0,
        fy: 50.0,
        cx: 31.5,
        cy: 23.5,
        skew: 0.0,
        distortion: Distortion::None,
    }
}

/// An image whose columns left of `split` are `left` and the rest `right`.
fn frame(split: u32, left: [u8; 3], right: [u8; 3]) -> EoFrame {
    let mut rgb = Vec::with_capacity((3 * W * H) as usize);
    for _ in 0..H {
        for x in 0..W {
            rgb.extend_from_slice(if x < split { &left } else { &right });
        }
    }
    EoFrame {
        width: W,
        height: H,
        rgb,
        timestamp_ns: 0,
        exposure: None,
    }
}

/// A view 5 m in front of the z = 0 plane around the mesh origin, looking along +z:
/// world x maps to pixel 31.5 + 10 x (x relative to the origin).
fn view<'a>(id: u32, camera: &'a PinholeCamera, image: Option<&'a EoFrame>) -> AcquisitionView<'a> {
    AcquisitionView {
        id,
        world_from_eo: Isometry3::translation(100.0, 200.0, -5.0),
        camera,
        image,
    }
}

fn near(a: Option<[f32; 3]>, b: [f32; 3]) -> bool {
    a.is_some_and(|a| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-6))
}

#[test]
fn a_triangle_takes_the_colour_its_centroid_projects_on() {
    // 4 × 3 cells over x ∈ [-2, 2], y ∈ [-1.5, 1.5]; the image red left of pixel
    // column 32 (x < 0), green right of it.
    let m = grid(4, 3, -2.0, -1.5);
    let cam = camera();
    let image = frame(32, [255, 0, 0], [0, 255, 0]);
    let views = [view(7, &cam, Some(&image))];
    let seen_by = vec![vec![7]; m.triangles.len()];
    let config = HoleFillConfig {
        occlusion_boundary: false,
        ..HoleFillConfig::default()
    };
    let colours = triangle_colours(&m, &seen_by, &views, &config);
    for (t, c) in colours.iter().enumerate() {
        let cell = t as u32 / 2;
        match cell % 4 {
            0 | 1 => assert!(near(*c, RED), "{t}: {c:?}"),
            _ => assert!(near(*c, GREEN), "{t}: {c:?}"),
        }
    }
    // The boundary skip changes nothing with one view: every sample would be skipped
    // at the border, so all are used.
    assert_eq!(
        triangle_colours(&m, &seen_by, &views, &HoleFillConfig::default()),
        colours
    );
}

#[test]
fn samples_next_to_an_occlusion_boundary_are_skipped_when_another_view_has_one() {
    let m = grid(4, 3, -2.0, -1.5);
    let cam = camera();
    let red_green = frame(32, [255, 0, 0], [0, 255, 0]);
    let blue = frame(0, [0, 0, 0], [0, 0, 255]);
    let views = [view(1, &cam, Some(&red_green)), view(2, &cam, Some(&blue))];
    let n = m.triangles.len();
    // Cell (1, 1) is interior: its triangles 10 and 11 share every edge. View 2 does
    // not see 11, so 10 sits at view 2's occlusion boundary.
    let mut seen_by = vec![vec![1, 2]; n];
    seen_by[11] = vec![1];
    // No view sees triangle 0.
    seen_by[0] = Vec::new();
    let colours = triangle_colours(&m, &seen_by, &views, &HoleFillConfig::default());
    assert!(near(colours[10], RED), "{:?}", colours[10]);
    assert!(
        near(colours[11], RED),
        "seen by view 1 only: {:?}",
        colours[11]
    );
    // Interior and away from any boundary of either view: both samples.
    assert!(near(colours[12], [0.0, 0.5, 0.5]), "{:?}", colours[12]);
    // On the mesh border both views' samples would be skipped: both are used.
    assert!(near(colours[2], [0.5, 0.0, 0.5]), "{:?}", colours[2]);
    assert_eq!(colours[0], None);
    // With the skip off, triangle 10 averages both views.
    let off = HoleFillConfig {
        occlusion_boundary: false,
        ..HoleFillConfig::default()
    };
    let colours = triangle_colours(&m, &seen_by, &views, &off);
    assert!(near(colours[10], [0.5, 0.0, 0.5]), "{:?}", colours[10]);
}

#[test]
fn views_without_image_or_unknown_give_no_sample() {
    let m = grid(4, 3, -2.0, -1.5);
    let cam = camera();
    let image = frame(32, [255, 0, 0], [0, 255, 0]);
    let views = [view(1, &cam, None), view(2, &cam, Some(&image))];
    let n = m.triangles.len();
    let mut seen_by = vec![vec![1, 9]; n];
    seen_by[10] = vec![1, 2, 9];
    // Shorter than the triangles: the rest count as unseen.
    seen_by.truncate(n - 1);
    let colours = triangle_colours(&m, &seen_by, &views, &HoleFillConfig::default());
    assert_eq!(colours.len(), n);
    for (t, c) in colours.iter().enumerate() {
        if t == 10 {
            assert!(near(*c, RED), "{c:?}");
        } else {
            assert_eq!(*c, None, "{t}");
        }
    }
}

#[test]
fn sampling_is_bilinear_between_pixel_centres() {
    // Red up to column 31, green from 32: a point at pixel x = 31.5 is half each.
    let image = frame(32, [255, 0, 0], [0, 255, 0]);
    let mid = bilinear(&image, &Vector2::new(31.5, 10.0)).unwrap();
    assert!((mid[0] - 0.5).abs() < 1e-12 && (mid[1] - 0.5).abs() < 1e-12);
    let quarter = bilinear(&image, &Vector2::new(31.25, 10.0)).unwrap();
    assert!((quarter[0] - 0.75).abs() < 1e-12 && (quarter[1] - 0.25).abs() < 1e-12);
    // Clamped at the border; a frame whose bytes do not match its size gives nothing.
    assert_eq!(
        bilinear(&image, &Vector2::new(-0.4, -0.4)),
        Some([1.0, 0.0, 0.0])
    );
    let short = EoFrame {
        rgb: vec![0; 5],
        ..image.clone()
    };
    assert_eq!(bilinear(&short, &Vector2::new(1.0, 1.0)), None);
}

#[test]
fn the_vertex_table_lists_each_triangle_once_per_vertex() {
    let table = VertexTriangles::build(&[[0, 1, 2], [2, 1, 3], [3, 3, 4]], 5);
    assert_eq!(table.around(0), &[0]);
    assert_eq!(table.around(1), &[0, 1]);
    assert_eq!(table.around(2), &[0, 1]);
    assert_eq!(table.around(3), &[1, 2]);
    assert_eq!(table.around(4), &[2]);
    assert!(table.around(5).is_empty());
}

#[test]
fn a_corner_takes_the_closest_colour_around_it_before_the_triangles() {
    // Hole H = [a, b, c]. Around a only the far sliver A (red); B (blue) touches b and
    // its centroid is nearer a than A's is. Nothing coloured touches c. H2 touches H
    // at c only, and its corner e lies next to a.
    let positions = vec![
        [0.0, 0.0, 0.0],   // 0 a
        [1.0, 0.0, 0.0],   // 1 b
        [0.5, 1.0, 0.0],   // 2 c
        [-10.0, 0.0, 0.0], // 3
        [-10.0, -1.0, 0.0],
        [0.5, -0.5, 0.0], // 5
        [1.5, -0.5, 0.0],
        [0.2, 1.5, 0.0],  // 7 g
        [-0.3, 0.2, 0.0], // 8 e
    ];
    let triangles = vec![[0, 3, 4], [1, 5, 6], [0, 1, 2], [2, 7, 8]];
    let m = mesh(positions, triangles);
    let colours = vec![Some(RED), Some(BLUE), None, None];
    let fill = fill_holes(&m, &colours, &HoleFillConfig::default()).unwrap();
    // a: the only coloured triangle around it, though B's centroid is nearer; b: B;
    // c: none around it, so the closest around the hole, B.
    assert_eq!(fill.corner_colours[2], Some([RED, BLUE, BLUE]));
    assert_eq!(fill.round[2], 1);
    // H2 copies H's corner colours: c's own at c, the nearest corner's elsewhere.
    assert_eq!(fill.corner_colours[3], Some([BLUE, BLUE, RED]));
    assert_eq!(fill.round[3], 2);
}
