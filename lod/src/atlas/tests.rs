//! The atlas's layout pieces on their own: flattening, charts, shelves.

use super::*;

#[test]
fn a_flat_triangle_keeps_its_edges_and_fits_its_rectangle() {
    let f = flatten([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.2, 2.0, 0.0]]);
    let len = |a: [f64; 2], b: [f64; 2]| ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt();
    assert!((len(f.flat[0], f.flat[1]) - 1.0).abs() < 1e-6);
    assert!((len(f.flat[1], f.flat[2]) - (0.64f64 + 4.0).sqrt()).abs() < 1e-6);
    assert!((len(f.flat[0], f.flat[2]) - (0.04f64 + 4.0).sqrt()).abs() < 1e-6);
    for c in f.flat {
        assert!(c[0] >= 0.0 && c[0] <= f.size_m[0] + 1e-12);
        assert!(c[1] >= 0.0 && c[1] <= f.size_m[1] + 1e-12);
    }
}

#[test]
fn triangles_repeating_a_vertex_are_laid_out_without_panic() {
    let mut mesh = SurfaceMesh::empty([0.0; 3]);
    mesh.positions = vec![
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [1.0, 1.0, 0.0],
    ];
    mesh.colours = vec![[10, 20, 30]; 4];
    mesh.triangles = vec![[0, 0, 0], [0, 0, 0], [0, 1, 2], [2, 1, 3], [1, 1, 2]];
    let params = AtlasParams {
        texel_m: 0.1,
        max_px: 64,
        lod: 1,
        search_m: 0.0,
    };
    let atlas = build_atlas(&mesh, &[], &params).unwrap_or_else(|| panic!("an atlas"));
    assert_eq!(atlas.mesh.triangle_count(), 5);
    assert_eq!(atlas.texture.uvs.len(), atlas.mesh.vertex_count());
    // The unit square's two halves share their diagonal: one chart, four vertices.
    assert!(atlas.charts.len() < 5);
    // No field: every texel of every chart is the vertex colour.
    let w = atlas.texture.width;
    for c in &atlas.charts {
        for j in c.y..c.y + c.height {
            for i in c.x..c.x + c.width {
                let at = ((j * w + i) * 3) as usize;
                assert_eq!(atlas.texture.rgb[at..at + 3], [10, 20, 30]);
            }
        }
    }
}

#[test]
fn degenerate_triangles_still_get_a_chart() {
    let f = flatten([[1.0, 1.0, 1.0]; 3]);
    assert_eq!(chart_size(f.size_m, 0.1), [1 + 2 * GUTTER_PX; 2]);
    assert_eq!(
        closest_barycentric(&f.flat, [5.0, 5.0]).iter().sum::<f64>(),
        1.0
    );
}

#[test]
fn shelves_never_overlap() {
    let sizes: Vec<[u32; 2]> = (0..50).map(|i| [3 + i % 7, 3 + (i * 5) % 11]).collect();
    let (charts, height) = shelf_pack(&sizes, 32);
    for (i, a) in charts.iter().enumerate() {
        assert!(a.x + a.width <= 32 && a.y + a.height <= height);
        for b in &charts[i + 1..] {
            let apart = a.x + a.width <= b.x
                || b.x + b.width <= a.x
                || a.y + a.height <= b.y
                || b.y + b.height <= a.y;
            assert!(apart, "{a:?} {b:?}");
        }
    }
}
