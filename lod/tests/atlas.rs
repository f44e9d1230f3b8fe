//! Tiles' texture atlases over a painted plane whose colour is known everywhere: the
//! atlas, read back through each corner's coordinates as a GPU would (bilinear), shows
//! the paint to within a few levels even on a coarse tile whose vertex colours cannot
//! follow its stripes; every coordinate lies in [0, 1], the charts never overlap and
//! a bilinear tap inside a triangle reads only its own chart, border included.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
#![allow(clippy::needless_range_loop)] // x, y and z side by side read clearer indexed

mod support;

use std::sync::OnceLock;

use texel_lod::atlas::{AtlasParams, GUTTER_PX, build_atlas};
use texel_lod::{LodConfig, LodModel, LodNode, TileTexture};
use texel_surface::{Sample, Tsdf, TsdfConfig};

const SIDE_M: f64 = 25.6;
/// Stripes across x (period 1.6 m: four level-2 voxels, sixteen leaf voxels) and a
/// slower wave across y.
fn paint(p: [f64; 3]) -> [f64; 3] {
    let tau = std::f64::consts::TAU;
    [
        128.0 + 100.0 * (tau * p[0] / 1.6).sin(),
        128.0 + 80.0 * (tau * p[1] / 6.4).cos(),
        100.0,
    ]
}

fn config() -> LodConfig {
    LodConfig {
        tile_voxels: 32,
        tile_triangle_budget: 64,
        max_lod: 4,
        ..LodConfig::default()
    }
}

/// The plane z = 0 over [0, SIDE_M]² painted by `colour`, seen straight down point
/// by point.
fn plane_samples(colour: fn([f64; 3]) -> [f64; 3]) -> Vec<Sample> {
    let step = 0.05;
    let n = (SIDE_M / step) as i64;
    let mut samples = Vec::new();
    for i in 0..n {
        for j in 0..n {
            let p = [(i as f64 + 0.5) * step, (j as f64 + 0.5) * step, 0.0];
            samples.push(Sample {
                point_m: p,
                centre_m: [p[0], p[1], 2.0],
                weight: 1.0,
                colour: Some(colour(p).map(|v| v.round() as u8)),
            });
        }
    }
    samples
}

/// The plane, built in one go.
fn plane_model() -> &'static (LodModel, Vec<Tsdf>) {
    static MODEL: OnceLock<(LodModel, Vec<Tsdf>)> = OnceLock::new();
    MODEL.get_or_init(|| {
        let config = config();
        let mut field = Tsdf::new(TsdfConfig {
            voxel_m: config.leaf_voxel_m,
            truncation_voxels: config.truncation_voxels,
        })
        .unwrap();
        field.integrate(&plane_samples(paint));
        let mut model = LodModel::from_field(field, &config).unwrap();
        model.rebuild(usize::MAX);
        let fields = (0..=config.max_lod)
            .map_while(|k| model.field(k).cloned())
            .collect();
        (model, fields)
    })
}

fn nodes() -> Vec<LodNode> {
    let (model, _) = plane_model();
    model
        .hierarchy()
        .unwrap()
        .nodes
        .into_values()
        .filter(|n| !n.mesh.is_empty())
        .collect()
}

/// The tiles with an atlas: all but the finest level's, whose vertices already
/// carry the finest colour there is.
fn textured() -> Vec<LodNode> {
    let nodes = nodes();
    for n in &nodes {
        assert_eq!(n.texture.is_some(), n.id.lod > 0, "{:?}", n.id);
    }
    nodes.into_iter().filter(|n| n.texture.is_some()).collect()
}

/// The atlas at `uv` as a GPU samples it: bilinear between texel centres, clamped
/// at the edges.
fn bilinear(t: &TileTexture, uv: [f64; 2]) -> [f64; 3] {
    let (w, h) = (t.width as i64, t.height as i64);
    let x = uv[0] * w as f64 - 0.5;
    let y = uv[1] * h as f64 - 0.5;
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let texel = |i: i64, j: i64| {
        let (i, j) = (i.clamp(0, w - 1), j.clamp(0, h - 1));
        let at = ((j * w + i) * 3) as usize;
        [0, 1, 2].map(|c| f64::from(t.rgb[at + c]))
    };
    let (x0, y0) = (x0 as i64, y0 as i64);
    let mut out = [0.0; 3];
    for c in 0..3 {
        out[c] = (1.0 - fy) * ((1.0 - fx) * texel(x0, y0)[c] + fx * texel(x0 + 1, y0)[c])
            + fy * ((1.0 - fx) * texel(x0, y0 + 1)[c] + fx * texel(x0 + 1, y0 + 1)[c]);
    }
    out
}

fn error(a: [f64; 3], b: [f64; 3]) -> f64 {
    (0..3).map(|c| (a[c] - b[c]).abs()).fold(0.0, f64::max)
}

/// Points of each triangle to compare at: corners, centroid and three inner points,
/// as barycentric weights.
const PROBES: [[f64; 3]; 7] = [
    [1.0, 0.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, 0.0, 1.0],
    [1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0],
    [0.6, 0.2, 0.2],
    [0.2, 0.6, 0.2],
    [0.2, 0.2, 0.6],
];

/// Mean errors (atlas, vertex colours) against the paint over a tile's probes
/// inside the painted square (away from its edge, where the field thins out).
fn errors(node: &LodNode) -> (f64, f64, f64) {
    let texture = node.texture.as_ref().expect("an atlas");
    let mesh = &node.mesh;
    let (mut atlas, mut vertex, mut worst, mut count) = (0.0, 0.0, 0.0f64, 0.0);
    for t in &mesh.triangles {
        for b in PROBES {
            let world: [f64; 3] = [0, 1, 2].map(|a| {
                (0..3)
                    .map(|k| b[k] * mesh.world(t[k] as usize).unwrap()[a])
                    .sum()
            });
            if world[0] < 0.5
                || world[1] < 0.5
                || world[0] > SIDE_M - 0.5
                || world[1] > SIDE_M - 0.5
            {
                continue;
            }
            let uv = [0, 1].map(|c| {
                (0..3)
                    .map(|k| b[k] * f64::from(texture.uvs[t[k] as usize][c]))
                    .sum()
            });
            let colour: [f64; 3] = [0, 1, 2].map(|c| {
                (0..3)
                    .map(|k| b[k] * f64::from(mesh.colours[t[k] as usize][c]))
                    .sum()
            });
            let truth = paint(world);
            let e = error(bilinear(texture, uv), truth);
            atlas += e;
            worst = worst.max(e);
            vertex += error(colour, truth);
            count += 1.0;
        }
    }
    assert!(count > 0.0, "{:?}: nothing to compare", node.id);
    (atlas / count, vertex / count, worst)
}

#[test]
fn every_tile_atlas_shows_the_paint() {
    let nodes = textured();
    assert!(nodes.iter().any(|n| n.id.lod >= 2), "no coarse tile");
    for node in &nodes {
        let (atlas, _, worst) = errors(node);
        assert!(atlas < 6.0, "{:?}: mean atlas error {atlas}", node.id);
        assert!(worst < 30.0, "{:?}: worst atlas error {worst}", node.id);
    }
}

#[test]
fn a_coarse_tile_atlas_shows_stripes_its_vertex_colours_cannot() {
    let coarse: Vec<LodNode> = nodes().into_iter().filter(|n| n.id.lod >= 2).collect();
    assert!(!coarse.is_empty());
    for node in &coarse {
        let (atlas, vertex, _) = errors(node);
        eprintln!(
            "{:?}: {} triangles, atlas error {atlas:.1}, vertex colour error {vertex:.1}",
            node.id,
            node.mesh.triangle_count()
        );
        // Its vertices lie up to metres apart; the stripes repeat every 1.6 m.
        assert!(vertex > 20.0, "{:?}: vertex colour error {vertex}", node.id);
        assert!(
            atlas * 4.0 < vertex,
            "{:?}: atlas error {atlas}, vertex colour error {vertex}",
            node.id
        );
        // Its texels are finer than its own voxel: colour from a finer level.
        let texture = node.texture.as_ref().unwrap();
        assert!(texture.texel_m < node.voxel_m, "{:?}", node.id);
    }
}

#[test]
fn charts_are_disjoint_hold_their_triangles_and_are_filled() {
    let (_, fields) = plane_model();
    let config = config();
    for node in textured() {
        let texture = node.texture.as_ref().unwrap();
        let (w, h) = (texture.width, texture.height);
        assert!(w <= config.atlas_max_px && h <= config.atlas_max_px);
        assert_eq!(texture.rgb.len(), (w * h * 3) as usize);
        assert_eq!(texture.uvs.len(), node.mesh.vertex_count());
        assert!(
            texture
                .uvs
                .iter()
                .flatten()
                .all(|c| (0.0..=1.0).contains(c))
        );
        // The same mesh laid out again: the same charts and, from the same fields,
        // the same image (deterministic).
        let params = AtlasParams {
            texel_m: config.leaf_voxel_m * config.atlas_texel_voxels,
            max_px: config.atlas_max_px,
            lod: node.id.lod,
            search_m: node.geometric_error_m + fields[usize::from(node.id.lod)].truncation_m(),
        };
        let again = build_atlas(&node.mesh, fields, &params).unwrap();
        assert_eq!(&again.texture, texture);
        assert_eq!(again.mesh, node.mesh);
        let charts = &again.charts;
        assert_eq!(again.triangle_charts.len(), node.mesh.triangle_count());
        // Triangles pair up across shared longest edges: fewer charts than triangles.
        assert!(charts.len() < node.mesh.triangle_count());
        let mut owner = vec![usize::MAX; (w * h) as usize];
        for (n, c) in charts.iter().enumerate() {
            assert!(
                c.x + c.width <= w && c.y + c.height <= h,
                "{c:?} in {w}×{h}"
            );
            for j in c.y..c.y + c.height {
                for i in c.x..c.x + c.width {
                    let slot = &mut owner[(j * w + i) as usize];
                    assert_eq!(*slot, usize::MAX, "charts overlap at {i}, {j}");
                    *slot = n;
                    // Filled, gutter included: the paint's blue is 100 everywhere.
                    let at = ((j * w + i) * 3) as usize;
                    assert!(
                        texture.rgb[at + 2].abs_diff(100) <= 2,
                        "texel {i}, {j} of chart {c:?}: {:?}",
                        &texture.rgb[at..at + 3]
                    );
                }
            }
        }
        // Every bilinear tap at any point of a triangle reads its own chart, and the
        // triangle lies inside the chart's gutter.
        for (t, tri) in node.mesh.triangles.iter().enumerate() {
            let chart = again.triangle_charts[t];
            let c = charts[chart];
            for b in PROBES {
                let uv: [f64; 2] = [0, 1].map(|k| {
                    (0..3)
                        .map(|v| b[v] * f64::from(texture.uvs[tri[v] as usize][k]))
                        .sum()
                });
                let x = uv[0] * f64::from(w);
                let y = uv[1] * f64::from(h);
                let g = f64::from(GUTTER_PX);
                assert!(x >= f64::from(c.x) + g - 1e-3 && x <= f64::from(c.x + c.width) - g + 1e-3);
                assert!(
                    y >= f64::from(c.y) + g - 1e-3 && y <= f64::from(c.y + c.height) - g + 1e-3
                );
                let (i0, j0) = ((x - 0.5).floor() as i64, (y - 0.5).floor() as i64);
                for (i, j) in [(i0, j0), (i0 + 1, j0), (i0, j0 + 1), (i0 + 1, j0 + 1)] {
                    let (i, j) = (i.clamp(0, w as i64 - 1), j.clamp(0, h as i64 - 1));
                    assert_eq!(owner[(j as u32 * w + i as u32) as usize], chart);
                }
            }
        }
    }
}

#[test]
fn a_small_atlas_limit_coarsens_the_texel_and_still_fits() {
    let (model, fields) = plane_model();
    let node = model
        .hierarchy()
        .unwrap()
        .nodes
        .into_values()
        .filter(|n| !n.mesh.is_empty())
        .max_by_key(|n| n.id.lod)
        .unwrap();
    let params = |max_px| AtlasParams {
        texel_m: 0.1,
        max_px,
        // Colour may come from any level up to the coarsest, so the limit alone
        // decides the texel.
        lod: config().max_lod,
        search_m: 1.0,
    };
    // Halving the limit never makes the texel finer, and every atlas fits.
    let mut texels = Vec::new();
    for max_px in [1024, 512, 256, 128, 64, 32, 16] {
        let Some(atlas) = build_atlas(&node.mesh, fields, &params(max_px)) else {
            break;
        };
        assert!(atlas.texture.width <= max_px && atlas.texture.height <= max_px);
        texels.push(atlas.texture.texel_m);
    }
    eprintln!("{:?}: texels {texels:?}", node.id);
    assert!(texels.len() >= 2 && texels.len() < 7, "{texels:?}");
    assert!(texels.windows(2).all(|w| w[0] <= w[1]) && texels[0] < texels[texels.len() - 1]);
    // A limit no chart layout can meet leaves the tile to its vertex colours, as does
    // one met only at the tile's own voxel.
    assert!(build_atlas(&node.mesh, fields, &params(1)).is_none());
    let own = AtlasParams {
        lod: node.id.lod,
        ..params(16)
    };
    assert!(build_atlas(&node.mesh, fields, &own).is_none());
    let _ = support::HALF_WIDTH;
}

/// Scans arriving after a build: the coarse tiles are rebuilt, and their atlases show
/// the new colour, as a build from scratch of all the scans does.
#[test]
fn an_incremental_rebuild_repaints_the_atlases() {
    let grey = |_: [f64; 3]| [50.0, 50.0, 50.0];
    let mut model = LodModel::new(config()).unwrap();
    model.add_samples(&plane_samples(paint));
    model.rebuild(usize::MAX);
    let before = model.hierarchy().unwrap();
    // The same plane seen again, painted a flat grey: the fused colour moves halfway.
    model.add_samples(&plane_samples(grey));
    model.rebuild(usize::MAX);
    let after = model.hierarchy().unwrap();
    let mut scratch = LodModel::new(config()).unwrap();
    scratch.add_samples(&plane_samples(paint));
    scratch.add_samples(&plane_samples(grey));
    scratch.rebuild(usize::MAX);
    let scratch = scratch.hierarchy().unwrap();
    let mut coarse = 0;
    for (id, node) in &after.nodes {
        let (Some(old), Some(new)) = (before.nodes[id].texture.as_ref(), node.texture.as_ref())
        else {
            continue;
        };
        coarse += 1;
        assert!(old.rgb != new.rgb, "{id:?}: the atlas was not rebuilt");
        let mean = |t: &TileTexture| t.rgb.iter().map(|&v| f64::from(v)).sum::<f64>();
        assert!(mean(new) < mean(old), "{id:?}: not greyer after");
        assert_eq!(Some(new), scratch.nodes[id].texture.as_ref(), "{id:?}");
    }
    assert!(coarse > 0);
}
