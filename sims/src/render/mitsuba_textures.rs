//! Textures for the Mitsuba export: bitmaps shared by a material's shapes (checkers as
//! one texel per square, images at level 0) and textures baked per shape (noise,
//! bricks, and anything on a disk's polar coordinates).

use std::f64::consts::PI;
use std::io::Write;

use nalgebra::Matrix3;

use super::{AlbedoSpec, Item, MAX_BAKE_SIDE, MAX_CHECKER_SIDE, Writer, affine, rows9};
use crate::material::{Rgb, Texture};

impl Writer<'_> {
    pub(super) fn write_texels(
        &mut self,
        width: usize,
        height: usize,
        texel: impl Fn(usize, usize) -> Rgb,
    ) -> Result<String, String> {
        let name = format!("tex{}.f32", self.textures);
        let path = self.dir.join(&name);
        let file = std::fs::File::create(&path)
            .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
        let mut out = std::io::BufWriter::new(file);
        for j in 0..height {
            for i in 0..width {
                for c in texel(i, j) {
                    out.write_all(&c.to_le_bytes())
                        .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
                }
            }
        }
        out.flush()
            .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
        self.textures += 1;
        Ok(name)
    }

    /// The bitmap shared by every shape of a checker or image material, and the map
    /// from our uv (metres) to its coordinates.
    pub(super) fn material_bitmap(
        &mut self,
        texture: &Texture,
    ) -> Result<(AlbedoSpec, Matrix3<f64>), String> {
        match texture {
            Texture::Checker {
                square_m, squares, ..
            } => {
                let sq = *square_m;
                let (nx, ny, t, wrap) = match squares {
                    None => (
                        2,
                        2,
                        affine([[0.5 / sq, 0.0, 0.0], [0.0, 0.5 / sq, 0.0]]),
                        "repeat",
                    ),
                    Some([sx, sy]) => {
                        if sx + 2 > MAX_CHECKER_SIDE || sy + 2 > MAX_CHECKER_SIDE {
                            return Err(format!(
                                "a checkerboard of {sx}x{sy} squares is too large for a bitmap"
                            ));
                        }
                        let (w, h) = (f64::from(sx + 2), f64::from(sy + 2));
                        let (hx, hy) = (0.5 * f64::from(*sx), 0.5 * f64::from(*sy));
                        (
                            *sx + 2,
                            *sy + 2,
                            affine([
                                [1.0 / (sq * w), 0.0, (hx + 1.0) / w],
                                [0.0, 1.0 / (sq * h), (hy + 1.0) / h],
                            ]),
                            "clamp",
                        )
                    }
                };
                // Texel centres, back in metres, land inside one square each.
                let inv = t.try_inverse().ok_or("degenerate checker square size")?;
                let (w, h) = (nx as usize, ny as usize);
                let file = self.write_texels(w, h, |i, j| {
                    let s = (i as f64 + 0.5) / w as f64;
                    let tt = (j as f64 + 0.5) / h as f64;
                    let uv = inv * nalgebra::Vector3::new(s, tt, 1.0);
                    texture.sample([uv.x, uv.y], 0.0)
                })?;
                Ok((bitmap(file, w, h, "nearest", wrap), t))
            }
            Texture::Image { image, size_m } => {
                let (w, h) = (image.width() as usize, image.height() as usize);
                let (sx, sy) = (size_m[0], size_m[1]);
                // Ours: s = u / size_x + 0.5, t = 0.5 - v / size_y (row 0 at the top).
                let t = affine([[1.0 / sx, 0.0, 0.5], [0.0, -1.0 / sy, 0.5]]);
                let file = self.write_texels(w, h, |i, j| {
                    let s = (i as f64 + 0.5) / w as f64;
                    let tt = (j as f64 + 0.5) / h as f64;
                    texture.sample([(s - 0.5) * sx, (0.5 - tt) * sy], 0.0)
                })?;
                Ok((bitmap(file, w, h, "bilinear", "repeat"), t))
            }
            Texture::Constant(_) | Texture::Noise { .. } | Texture::Bricks(_) => {
                Err("not a bitmap texture".into())
            }
        }
    }

    /// Bakes a texture over the shape's uv range (noise and bricks).
    pub(super) fn bake_region(
        &mut self,
        texture: &Texture,
        item: &Item,
        a: &Matrix3<f64>,
    ) -> Result<AlbedoSpec, String> {
        let (u0, v0) = (item.uv_min[0], item.uv_min[1]);
        let (du, dv) = (
            (item.uv_max[0] - u0).max(1e-9),
            (item.uv_max[1] - v0).max(1e-9),
        );
        let finest = match texture {
            Texture::Noise {
                scale_m, octaves, ..
            } => scale_m / f64::from(1u32 << (*octaves).min(16)) / 2.0,
            Texture::Bricks(b) => bricks_texel_m(b),
            _ => du.max(dv) / MAX_BAKE_SIDE as f64,
        };
        let side = |d: f64| ((d / finest.max(1e-9)).ceil() as usize).clamp(2, MAX_BAKE_SIDE);
        let (w, h) = (side(du), side(dv));
        let footprint = (du / w as f64).max(dv / h as f64);
        let file = self.write_texels(w, h, |i, j| {
            let u = u0 + (i as f64 + 0.5) / w as f64 * du;
            let v = v0 + (j as f64 + 0.5) / h as f64 * dv;
            texture.sample([u, v], footprint)
        })?;
        let region = affine([[1.0 / du, 0.0, -u0 / du], [0.0, 1.0 / dv, -v0 / dv]]);
        Ok(with_to_uv(
            bitmap(file, w, h, "bilinear", item.bake_wrap),
            &(region * a),
        ))
    }

    /// Bakes a texture in a disk's polar uv: columns ρ / r, rows φ / 2π.
    pub(super) fn bake_disk(&mut self, texture: &Texture, r: f64) -> Result<AlbedoSpec, String> {
        let finest = match texture {
            Texture::Noise {
                scale_m, octaves, ..
            } => scale_m / f64::from(1u32 << (*octaves).min(16)) / 2.0,
            Texture::Checker { square_m, .. } => square_m / 64.0,
            Texture::Bricks(b) => bricks_texel_m(b),
            _ => r / 256.0,
        };
        let w = ((r / finest.max(1e-9)).ceil() as usize).clamp(16, MAX_BAKE_SIDE);
        let h = ((2.0 * PI * r / finest.max(1e-9)).ceil() as usize).clamp(64, MAX_BAKE_SIDE);
        let footprint = finest.max(r / w as f64);
        let file = self.write_texels(w, h, |i, j| {
            let rho = (i as f64 + 0.5) / w as f64 * r;
            let phi = (j as f64 + 0.5) / h as f64 * 2.0 * PI;
            texture.sample([rho * phi.cos(), rho * phi.sin()], footprint)
        })?;
        Ok(bitmap(file, w, h, "bilinear", "clamp"))
    }
}

/// The texel a brick texture is baked at: a quarter of a joint, or an eighth of a
/// brick's height without joints (the bake is capped at [`MAX_BAKE_SIDE`] texels a
/// side).
fn bricks_texel_m(b: &crate::material::Bricks) -> f64 {
    if b.mortar_m > 0.0 {
        (0.25 * b.mortar_m).min(b.brick_m[1] / 8.0)
    } else {
        b.brick_m[1] / 8.0
    }
}

pub(super) fn bitmap(
    file: String,
    width: usize,
    height: usize,
    filter: &'static str,
    wrap: &'static str,
) -> AlbedoSpec {
    AlbedoSpec::Bitmap {
        file,
        width,
        height,
        filter,
        wrap,
        to_uv: rows9(&Matrix3::identity()),
    }
}

pub(super) fn with_to_uv(spec: AlbedoSpec, m: &Matrix3<f64>) -> AlbedoSpec {
    match spec {
        AlbedoSpec::Bitmap {
            file,
            width,
            height,
            filter,
            wrap,
            ..
        } => AlbedoSpec::Bitmap {
            file,
            width,
            height,
            filter,
            wrap,
            to_uv: rows9(m),
        },
        other => other,
    }
}
