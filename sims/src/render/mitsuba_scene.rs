//! Export of a scene's world for the Mitsuba backend: `scene.json` (shapes with their
//! transforms, BSDFs, lights, ambient, background), PLY meshes and raw float32
//! texture arrays, in a directory the Python side reads.
//!
//! Mitsuba works in f32, so every position is written relative to the centre of the
//! scene's bounds (`offset`); rays are sent relative to it too.
//!
//! Geometry is exact: parallelograms become `rectangle`s, unbounded planes very large
//! rectangles, spheres `sphere`s, cylinders a `cylinder` and two `disk` caps, triangles
//! one PLY mesh per (object, material). Textures keep our texture coordinates (metres
//! on the surface): each shape's native Mitsuba `uv` maps to them by an affine map
//! (the sphere and cylinder frames are turned half a turn so that Mitsuba's longitude
//! seam falls on ours), composed with the texture's own map into the bitmap's `to_uv`.
//! Checkerboards become bitmaps of one texel per square (nearest lookup: exact),
//! images their level-0 texels (bilinear, as ours at level 0); noise and bricks, and any texture
//! on a disk (polar `uv`), is baked per shape at a resolution bounded by
//! [`MAX_BAKE_SIDE`].

use std::collections::HashMap;
use std::f64::consts::PI;
use std::path::Path;

use nalgebra::{Matrix3, Point3, Vector3};
use serde::Serialize;

use crate::geometry::{Primitive, Shape};
use crate::light::Light;
use crate::material::{Rgb, Texture};
use crate::world::World;
use textures::with_to_uv;

/// Largest side of a baked texture (texels).
pub const MAX_BAKE_SIDE: usize = 1024;
/// Largest checkerboard bitmap side (squares + border).
const MAX_CHECKER_SIDE: u32 = 8192;
/// Half-side of the rectangle standing for an unbounded plane, as a multiple of the
/// scene's extent (at least [`MIN_PLANE_HALF_SIDE_M`]). Larger is worse: Mitsuba's
/// texture coordinates are f32 fractions of the rectangle (0.1 mm resolution at
/// 1 km), and a directional light's shadow rays start at the scene's bounding sphere,
/// where f32 offsets grow with its radius (at 1000 km they shadow everything).
const PLANE_EXTENT_FACTOR: f64 = 100.0;
const MIN_PLANE_HALF_SIDE_M: f64 = 1000.0;

#[derive(Serialize)]
struct SceneFile {
    version: u32,
    ambient: Rgb,
    background: Rgb,
    shapes: Vec<ShapeSpec>,
    bsdfs: Vec<BsdfSpec>,
    lights: Vec<LightSpec>,
}

#[derive(Serialize)]
struct ShapeSpec {
    kind: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    to_world: Option<[f64; 16]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    file: Option<String>,
    bsdf: usize,
}

#[derive(Serialize)]
struct BsdfSpec {
    albedo: AlbedoSpec,
    /// Blinn-Phong `k_s` of the material (the request scales it).
    specular: f32,
    /// Beckmann roughness matching the Blinn-Phong exponent: `sqrt(2 / (n + 2))`.
    alpha: f64,
}

#[derive(Serialize, Clone)]
#[serde(untagged)]
enum AlbedoSpec {
    Rgb {
        rgb: Rgb,
    },
    Bitmap {
        file: String,
        width: usize,
        height: usize,
        filter: &'static str,
        wrap: &'static str,
        /// Row-major 3x3 affine map from the shape's native uv to bitmap coordinates.
        to_uv: [f64; 9],
    },
}

#[derive(Serialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
enum LightSpec {
    Directional {
        /// Where the light travels.
        direction: [f64; 3],
        irradiance: Rgb,
    },
    Point {
        position: [f64; 3],
        intensity: Rgb,
    },
}

/// What the Rust side needs to turn Mitsuba's answers into echoes.
#[derive(Debug, Clone)]
pub struct ExportedScene {
    /// Subtracted from every world position sent to Mitsuba.
    pub offset: Vector3<f64>,
    /// `(object, material)` of each exported shape, by the index Mitsuba reports.
    pub shapes: Vec<(u32, u32)>,
    /// Shapes, bitmaps and meshes written.
    pub shape_count: usize,
    pub texture_count: usize,
}

/// How a shape's native Mitsuba uv relates to our texture coordinates (metres).
#[derive(Clone, Copy)]
enum NativeUv {
    /// `uv_m = A · (u, v, 1)`.
    Affine(Matrix3<f64>),
    /// A disk of this radius: native uv = (ρ / radius, φ / 2π), ours = local (x, y).
    Disk(f64),
}

/// One shape to write.
struct Item {
    kind: &'static str,
    to_world: Option<[f64; 16]>,
    file: Option<String>,
    native: NativeUv,
    /// Range of our uv over the shape (for baking).
    uv_min: [f64; 2],
    uv_max: [f64; 2],
    /// Wrap mode of a texture baked over `uv_min..uv_max`.
    bake_wrap: &'static str,
    object: u32,
    material: u32,
}

fn affine(m: [[f64; 3]; 2]) -> Matrix3<f64> {
    Matrix3::new(
        m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], 0.0, 0.0, 1.0,
    )
}

fn rows9(m: &Matrix3<f64>) -> [f64; 9] {
    [
        m[(0, 0)],
        m[(0, 1)],
        m[(0, 2)],
        m[(1, 0)],
        m[(1, 1)],
        m[(1, 2)],
        m[(2, 0)],
        m[(2, 1)],
        m[(2, 2)],
    ]
}

/// Row-major 4x4 with the given columns and translation.
fn to_world(c0: Vector3<f64>, c1: Vector3<f64>, c2: Vector3<f64>, p: Vector3<f64>) -> [f64; 16] {
    [
        c0.x, c1.x, c2.x, p.x, c0.y, c1.y, c2.y, p.y, c0.z, c1.z, c2.z, p.z, 0.0, 0.0, 0.0, 1.0,
    ]
}

fn lumen(v: Rgb, s: f32) -> Rgb {
    [v[0] * s, v[1] * s, v[2] * s]
}

struct Writer<'a> {
    dir: &'a Path,
    world: &'a World,
    offset: Vector3<f64>,
    plane_half_side_m: f64,
    /// Region baked for unbounded planes: half-side around the plane's origin.
    plane_bake_half_m: f64,
    bsdfs: Vec<BsdfSpec>,
    shapes: Vec<ShapeSpec>,
    ids: Vec<(u32, u32)>,
    /// Per material: the shared bitmap and the map from our uv to its coordinates.
    material_bitmaps: HashMap<u32, (AlbedoSpec, Matrix3<f64>)>,
    textures: usize,
}

/// Writes `world` into `dir` for `mitsuba_render.py`.
pub fn export(world: &World, dir: &Path) -> Result<ExportedScene, String> {
    let bounds = world.bvh.bounds();
    let (offset, extent) = match bounds {
        Some(b) if b.min.iter().chain(&b.max).all(|v| v.is_finite()) => (
            Vector3::new(b.centroid(0), b.centroid(1), b.centroid(2)),
            (0..3).map(|a| b.max[a] - b.min[a]).fold(0.0, f64::max),
        ),
        _ => (Vector3::zeros(), 100.0),
    };
    let mut w = Writer {
        dir,
        world,
        offset,
        plane_half_side_m: (PLANE_EXTENT_FACTOR * extent).max(MIN_PLANE_HALF_SIDE_M),
        plane_bake_half_m: extent.max(1.0),
        bsdfs: Vec::new(),
        shapes: Vec::new(),
        ids: Vec::new(),
        material_bitmaps: HashMap::new(),
        textures: 0,
    };
    // Triangles: one mesh per (object, material), in first-seen order.
    let mut meshes: Vec<((u32, u32), Vec<&Primitive>)> = Vec::new();
    let mut mesh_index: HashMap<(u32, u32), usize> = HashMap::new();
    for p in world.bvh.primitives() {
        if let Shape::Triangle { .. } = p.shape {
            let key = (p.object, p.material);
            let i = *mesh_index.entry(key).or_insert_with(|| {
                meshes.push((key, Vec::new()));
                meshes.len() - 1
            });
            meshes[i].1.push(p);
        } else {
            for item in w.items(p) {
                w.add(item)?;
            }
        }
    }
    for ((object, material), tris) in &meshes {
        let item = w.mesh(*object, *material, tris)?;
        w.add(item)?;
    }
    let lights = world
        .lighting
        .lights
        .iter()
        .map(|l| match l {
            // Mitsuba's diffuse BSDF is albedo/π: π times our irradiance gives our
            // albedo · E · cos.
            Light::Directional {
                towards_light,
                color,
                intensity,
                ..
            } => LightSpec::Directional {
                direction: (-towards_light).into(),
                irradiance: lumen(*color, intensity * std::f32::consts::PI),
            },
            Light::Point {
                position,
                color,
                intensity,
                ..
            } => LightSpec::Point {
                position: (position.coords - offset).into(),
                intensity: lumen(*color, intensity * std::f32::consts::PI),
            },
        })
        .collect();
    let file = SceneFile {
        version: 1,
        ambient: world.lighting.ambient,
        background: world.background,
        shapes: std::mem::take(&mut w.shapes),
        bsdfs: std::mem::take(&mut w.bsdfs),
        lights,
    };
    let json = serde_json::to_vec(&file).map_err(|e| format!("scene.json: {e}"))?;
    std::fs::write(dir.join("scene.json"), json)
        .map_err(|e| format!("cannot write {}: {e}", dir.join("scene.json").display()))?;
    Ok(ExportedScene {
        offset,
        shape_count: w.ids.len(),
        shapes: w.ids,
        texture_count: w.textures,
    })
}

impl Writer<'_> {
    fn rel(&self, p: &Point3<f64>) -> Vector3<f64> {
        p.coords - self.offset
    }

    /// The Mitsuba shapes of one non-triangle primitive.
    fn items(&self, p: &Primitive) -> Vec<Item> {
        let (object, material) = (p.object, p.material);
        let item = |kind, m: [f64; 16], native, uv_min, uv_max| Item {
            kind,
            to_world: Some(m),
            file: None,
            native,
            uv_min,
            uv_max,
            bake_wrap: "clamp",
            object,
            material,
        };
        match &p.shape {
            Shape::Parallelogram {
                corner,
                edge_u,
                edge_v,
                normal,
                ..
            } => {
                let (lu, lv) = (edge_u.norm(), edge_v.norm());
                let centre = self.rel(corner) + 0.5 * (edge_u + edge_v);
                // Local x in [-1, 1] spans edge_u; native u = (x + 1) / 2 = a.
                let m = to_world(0.5 * edge_u, 0.5 * edge_v, *normal, centre);
                let a = affine([[lu, 0.0, -0.5 * lu], [0.0, lv, -0.5 * lv]]);
                vec![item(
                    "rectangle",
                    m,
                    NativeUv::Affine(a),
                    [-0.5 * lu, -0.5 * lv],
                    [0.5 * lu, 0.5 * lv],
                )]
            }
            Shape::InfinitePlane {
                origin,
                axis_u,
                axis_v,
                normal,
            } => {
                let l = self.plane_half_side_m;
                let m = to_world(axis_u * l, axis_v * l, *normal, self.rel(origin));
                let a = affine([[2.0 * l, 0.0, -l], [0.0, 2.0 * l, -l]]);
                let b = self.plane_bake_half_m;
                // Around the point of the plane nearest the scene's centre.
                let c = self.offset - origin.coords;
                let (cu, cv) = (c.dot(axis_u), c.dot(axis_v));
                vec![Item {
                    bake_wrap: "repeat",
                    ..item(
                        "rectangle",
                        m,
                        NativeUv::Affine(a),
                        [cu - b, cv - b],
                        [cu + b, cv + b],
                    )
                }]
            }
            Shape::Sphere {
                center,
                radius,
                axis_x,
                axis_y,
                axis_z,
            } => {
                let r = *radius;
                // Turned half a turn about z: Mitsuba's φ' in [0, 2π) is our
                // longitude + π, so both seams are at longitude ±π.
                let m = to_world(-axis_x * r, -axis_y * r, axis_z * r, self.rel(center));
                let a = affine([[2.0 * PI * r, 0.0, -PI * r], [0.0, PI * r, 0.0]]);
                vec![item(
                    "sphere",
                    m,
                    NativeUv::Affine(a),
                    [-PI * r, 0.0],
                    [PI * r, PI * r],
                )]
            }
            Shape::Cylinder {
                center,
                radius,
                half_height,
                axis_x,
                axis_y,
                axis_z,
            } => {
                let (r, h) = (*radius, *half_height);
                let c = self.rel(center);
                let side = to_world(-axis_x * r, -axis_y * r, axis_z * (2.0 * h), c - axis_z * h);
                let a = affine([[2.0 * PI * r, 0.0, -PI * r], [0.0, 2.0 * h, -h]]);
                let mut out = vec![item(
                    "cylinder",
                    side,
                    NativeUv::Affine(a),
                    [-PI * r, -h],
                    [PI * r, h],
                )];
                for sign in [-1.0, 1.0] {
                    let m = to_world(
                        axis_x * r,
                        axis_y * r,
                        axis_z * sign,
                        c + axis_z * (sign * h),
                    );
                    out.push(item("disk", m, NativeUv::Disk(r), [-r, -r], [r, r]));
                }
                out
            }
            Shape::Triangle { .. } => Vec::new(),
        }
    }

    /// A PLY mesh of triangles (three vertices each, so per-triangle uv stay exact).
    fn mesh(&mut self, object: u32, material: u32, tris: &[&Primitive]) -> Result<Item, String> {
        let name = format!("mesh{}.ply", self.ids.len());
        let path = self.dir.join(&name);
        let mut bytes = Vec::with_capacity(64 + tris.len() * (3 * 20 + 13));
        let header = format!(
            "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\n\
             property float y\nproperty float z\nproperty float u\nproperty float v\n\
             element face {}\nproperty list uchar uint vertex_indices\nend_header\n",
            3 * tris.len(),
            tris.len()
        );
        bytes.extend_from_slice(header.as_bytes());
        let (mut uv_min, mut uv_max) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for p in tris {
            if let Shape::Triangle { v0, e1, e2, uv, .. } = &p.shape {
                let v0 = self.rel(v0);
                for (k, v) in [v0, v0 + e1, v0 + e2].iter().enumerate() {
                    for c in [v.x, v.y, v.z, uv[k][0], uv[k][1]] {
                        bytes.extend_from_slice(&(c as f32).to_le_bytes());
                    }
                    for a in 0..2 {
                        uv_min[a] = uv_min[a].min(uv[k][a]);
                        uv_max[a] = uv_max[a].max(uv[k][a]);
                    }
                }
            }
        }
        for i in 0..tris.len() as u32 {
            bytes.push(3);
            for k in 0..3 {
                bytes.extend_from_slice(&(3 * i + k).to_le_bytes());
            }
        }
        std::fs::write(&path, bytes)
            .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
        Ok(Item {
            kind: "mesh",
            to_world: None,
            file: Some(name),
            native: NativeUv::Affine(Matrix3::identity()),
            uv_min,
            uv_max,
            bake_wrap: "clamp",
            object,
            material,
        })
    }

    fn add(&mut self, item: Item) -> Result<(), String> {
        let material = self
            .world
            .materials
            .get(item.material as usize)
            .ok_or_else(|| format!("material {} does not exist", item.material))?;
        let albedo = self.albedo(&item, &material.texture)?;
        self.bsdfs.push(BsdfSpec {
            albedo,
            specular: material.specular,
            alpha: (2.0 / (f64::from(material.shininess.max(1.0)) + 2.0)).sqrt(),
        });
        self.shapes.push(ShapeSpec {
            kind: item.kind,
            to_world: item.to_world,
            file: item.file,
            bsdf: self.bsdfs.len() - 1,
        });
        self.ids.push((item.object, item.material));
        Ok(())
    }

    fn albedo(&mut self, item: &Item, texture: &Texture) -> Result<AlbedoSpec, String> {
        if let Texture::Constant(c) = texture {
            return Ok(AlbedoSpec::Rgb { rgb: *c });
        }
        let a = match item.native {
            NativeUv::Affine(a) => a,
            NativeUv::Disk(r) => return self.bake_disk(texture, r),
        };
        if let Texture::Noise { .. } | Texture::Bricks(_) = texture {
            return self.bake_region(texture, item, &a);
        }
        let (spec, t) = match self.material_bitmaps.get(&item.material) {
            Some(found) => found.clone(),
            None => {
                let made = self.material_bitmap(texture)?;
                self.material_bitmaps.insert(item.material, made.clone());
                made
            }
        };
        Ok(with_to_uv(spec, &(t * a)))
    }
}

#[path = "mitsuba_textures.rs"]
mod textures;

#[cfg(test)]
#[path = "mitsuba_scene_tests.rs"]
mod tests;
