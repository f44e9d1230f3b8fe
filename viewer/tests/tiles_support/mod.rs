//! Shared helpers of the tile tests: a small street with analytic truth (flat ground
//! between two facades, as `lod/tests/support`), fused and built into a hierarchy;
//! cameras along it; and an independent CPU rasteriser of tiles.
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use texel_lod::{Hierarchy, LodConfig, LodNode, build_from_field};
use texel_surface::{Sample, Tsdf, TsdfConfig};
use texel_viewer::camera::VirtualCamera;
use texel_viewer::tiles::look_at;

#[path = "../../../lod/tests/support/mod.rs"]
mod street;

/// Where nothing is drawn: no tile colour has full red and no green.
pub const BACKGROUND: [f32; 3] = [1.0, 0.0, 1.0];
pub const BACKGROUND_U8: [u8; 3] = [255, 0, 255];

/// A 1 m checker of three colours on every surface, so coarser levels (voxels up to
/// 1.6 m) blur it visibly; the ground's greens (green 200) apart from the facades'
/// colours (green at most 160).
fn colour_at(p: [f64; 3]) -> [u8; 3] {
    let ground = p[2].abs() < 0.05;
    let across = if ground { p[1] } else { p[2] };
    let band = (p[0].floor() as i64 + across.floor() as i64).rem_euclid(3) as u8;
    if ground {
        [60 + band * 60, 200, 60 + band * 40]
    } else {
        [60 + band * 70, 100 + band * 30, 210 - band * 70]
    }
}

/// Whether a rendered pixel shows the ground (its green).
pub fn is_ground(p: &image::Rgba<u8>) -> bool {
    p[1] >= 185 && [p[0], p[1], p[2]] != BACKGROUND_U8
}

/// Samples from a camera 1.5 m up every `step_m` along `length_m`, a fan of rays
/// cut at the ground or a facade within 12 m (the level-of-detail tests' street),
/// painted with the checker; everything shifted by `offset`.
pub fn street_samples(length_m: f64, step_m: f64, offset: [f64; 3]) -> Vec<Sample> {
    street::street_stops_coloured(length_m, step_m, offset, colour_at).concat()
}

/// Small tiles (3.2 m at the finest level) so a short street has four levels; 0.2 m
/// voxels, so the sparse test scans observe every finest voxel they pass.
pub fn config() -> LodConfig {
    LodConfig {
        leaf_voxel_m: 0.2,
        tile_voxels: 16,
        tile_triangle_budget: 1_500,
        ..LodConfig::default()
    }
}

pub fn street(length_m: f64, offset: [f64; 3]) -> Hierarchy {
    let config = config();
    let mut field = Tsdf::new(TsdfConfig {
        voxel_m: config.leaf_voxel_m,
        truncation_voxels: config.truncation_voxels,
    })
    .unwrap();
    field.integrate(&street_samples(length_m, 1.0, offset));
    build_from_field(field, &config).unwrap()
}

/// A camera (60 degrees, z up) at `eye` looking at `target`, both relative to
/// `offset`.
pub fn camera(
    eye: [f64; 3],
    target: [f64; 3],
    offset: [f64; 3],
    width: u32,
    height: u32,
) -> VirtualCamera {
    let add = |p: [f64; 3]| [0, 1, 2].map(|k| p[k] + offset[k]);
    VirtualCamera::new(
        look_at(add(eye), add(target), [0.0, 0.0, 1.0]).unwrap(),
        60.0,
        width,
        height,
    )
    .unwrap()
}

/// Pixels that are not the background.
pub fn covered(img: &image::RgbaImage) -> Vec<bool> {
    img.pixels()
        .map(|p| [p[0], p[1], p[2]] != BACKGROUND_U8)
        .collect()
}

/// A CPU z-buffer render of `nodes`: f64 throughout, triangles clipped at the near
/// plane, colours interpolated perspective-correctly. Per pixel the colour (0 to
/// 255) or `None`.
pub fn cpu_render(nodes: &[&LodNode], cam: &VirtualCamera) -> Vec<Option<[f64; 3]>> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut depth = vec![f64::INFINITY; w * h];
    let mut colour = vec![None; w * h];
    // Which node drew each pixel: a textured node's pixels hold texture coordinates
    // until its atlas is sampled below.
    let mut owner = vec![usize::MAX; w * h];
    let view_from_world = cam.view_from_world();
    let f = cam.focal_px();
    let (cx, cy) = (w as f64 * 0.5, h as f64 * 0.5);
    for (n, node) in nodes.iter().enumerate() {
        let mesh = &node.mesh;
        let texture = node.texture.as_ref();
        for tri in &mesh.triangles {
            let verts: Vec<([f64; 3], [f64; 3])> = tri
                .iter()
                .map(|&v| {
                    let p = mesh.world(v as usize).unwrap();
                    let q = view_from_world * nalgebra::Point3::from(p);
                    let c = match texture {
                        Some(t) => {
                            let uv = t.uvs[v as usize];
                            [f64::from(uv[0]), f64::from(uv[1]), 0.0]
                        }
                        None => mesh.colours[v as usize].map(f64::from),
                    };
                    ([q.x, q.y, q.z], c)
                })
                .collect();
            let poly = clip_near(&verts, cam.near_m);
            for k in 1..poly.len().saturating_sub(1) {
                raster(
                    [poly[0], poly[k], poly[k + 1]],
                    (w, h, f, cx, cy),
                    &mut depth,
                    (&mut colour, &mut owner, n),
                );
            }
        }
    }
    for (c, &n) in colour.iter_mut().zip(&owner) {
        if let (Some(value), Some(t)) = (c.as_mut(), nodes.get(n).and_then(|n| n.texture.as_ref()))
        {
            *value = bilinear(t, [value[0], value[1]]);
        }
    }
    colour
}

/// An atlas sampled as the GPU's linear, clamp-to-edge sampler does: between the
/// four nearest texel centres.
fn bilinear(t: &texel_lod::TileTexture, uv: [f64; 2]) -> [f64; 3] {
    let (w, h) = (i64::from(t.width), i64::from(t.height));
    let x = uv[0] * w as f64 - 0.5;
    let y = uv[1] * h as f64 - 0.5;
    let (fx, fy) = (x - x.floor(), y - y.floor());
    let (x0, y0) = (x.floor() as i64, y.floor() as i64);
    let texel = |i: i64, j: i64| {
        let at = ((j.clamp(0, h - 1) * w + i.clamp(0, w - 1)) * 3) as usize;
        [0, 1, 2].map(|c| f64::from(t.rgb[at + c]))
    };
    let (a, b, c, d) = (
        texel(x0, y0),
        texel(x0 + 1, y0),
        texel(x0, y0 + 1),
        texel(x0 + 1, y0 + 1),
    );
    [0, 1, 2].map(|k| {
        (1.0 - fy) * ((1.0 - fx) * a[k] + fx * b[k]) + fy * ((1.0 - fx) * c[k] + fx * d[k])
    })
}

type Vtx = ([f64; 3], [f64; 3]);

fn lerp(a: &Vtx, b: &Vtx, t: f64) -> Vtx {
    (
        [0, 1, 2].map(|k| a.0[k] + t * (b.0[k] - a.0[k])),
        [0, 1, 2].map(|k| a.1[k] + t * (b.1[k] - a.1[k])),
    )
}

fn clip_near(poly: &[Vtx], near: f64) -> Vec<Vtx> {
    let mut out = Vec::new();
    for i in 0..poly.len() {
        let (a, b) = (&poly[i], &poly[(i + 1) % poly.len()]);
        let (ina, inb) = (a.0[2] >= near, b.0[2] >= near);
        if ina {
            out.push(*a);
        }
        if ina != inb {
            let t = (near - a.0[2]) / (b.0[2] - a.0[2]);
            out.push(lerp(a, b, t));
        }
    }
    out
}

fn raster(
    t: [Vtx; 3],
    (w, h, f, cx, cy): (usize, usize, f64, f64, f64),
    depth: &mut [f64],
    (colour, owner, node): (&mut [Option<[f64; 3]>], &mut [usize], usize),
) {
    let s: Vec<[f64; 2]> = t
        .iter()
        .map(|v| [cx + f * v.0[0] / v.0[2], cy + f * v.0[1] / v.0[2]])
        .collect();
    let area =
        (s[1][0] - s[0][0]) * (s[2][1] - s[0][1]) - (s[2][0] - s[0][0]) * (s[1][1] - s[0][1]);
    if area.abs() < 1e-12 {
        return;
    }
    let x0 = s
        .iter()
        .map(|p| p[0])
        .fold(f64::INFINITY, f64::min)
        .floor()
        .max(0.0) as usize;
    let x1 = s
        .iter()
        .map(|p| p[0])
        .fold(f64::NEG_INFINITY, f64::max)
        .ceil()
        .min(w as f64) as usize;
    let y0 = s
        .iter()
        .map(|p| p[1])
        .fold(f64::INFINITY, f64::min)
        .floor()
        .max(0.0) as usize;
    let y1 = s
        .iter()
        .map(|p| p[1])
        .fold(f64::NEG_INFINITY, f64::max)
        .ceil()
        .min(h as f64) as usize;
    for y in y0..y1 {
        for x in x0..x1 {
            let p = [x as f64 + 0.5, y as f64 + 0.5];
            let edge = |a: [f64; 2], b: [f64; 2]| {
                (b[0] - a[0]) * (p[1] - a[1]) - (p[0] - a[0]) * (b[1] - a[1])
            };
            let b0 = edge(s[1], s[2]) / area;
            let b1 = edge(s[2], s[0]) / area;
            let b2 = edge(s[0], s[1]) / area;
            if b0 < 0.0 || b1 < 0.0 || b2 < 0.0 {
                continue;
            }
            // Perspective-correct: interpolate 1/z and attribute/z.
            let iz = [0, 1, 2].map(|k| 1.0 / t[k].0[2]);
            let inv = b0 * iz[0] + b1 * iz[1] + b2 * iz[2];
            let z = 1.0 / inv;
            let i = y * w + x;
            if z >= depth[i] {
                continue;
            }
            depth[i] = z;
            let c = [0, 1, 2].map(|k| {
                (b0 * iz[0] * t[0].1[k] + b1 * iz[1] * t[1].1[k] + b2 * iz[2] * t[2].1[k]) * z
            });
            colour[i] = Some(c);
            owner[i] = node;
        }
    }
}
