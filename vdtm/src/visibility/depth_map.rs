//! The per-view depth map visibility tests against (§5 step 4): the whole surface
//! rendered on the CPU with a z-buffer from one acquisition view, keeping the nearest
//! depth along the optical axis at every pixel.

use nalgebra::{Point3, Vector2, Vector3};

use crate::view::AcquisitionView;

/// Triangles are clipped to this depth in front of the centre of projection (metres)
/// before projection: a triangle reaching behind the camera (a ground polygon passing
/// beneath it) still occludes with the part in front.
const NEAR_M: f64 = 1.0e-3;

/// Below this screen-space doubled area (depth-map pixels²) a triangle is seen
/// edge-on and covers no pixel centre worth writing.
const MIN_SCREEN_AREA: f64 = 1.0e-12;

/// A pixel centre on a triangle's edge belongs to it up to this barycentric slack, so
/// neighbouring triangles leave no gap between them.
const EDGE_SLACK: f64 = 1.0e-9;

/// A view's context: its depth map, the projection's domain bound computed once, and
/// its centre of projection.
pub(super) struct ViewDepth<'v, 'a> {
    pub view: &'v AcquisitionView<'a>,
    pub centre: Point3<f64>,
    max_r2: Option<f64>,
    map: DepthMap,
}

impl<'v, 'a> ViewDepth<'v, 'a> {
    /// Renders every triangle (`None` entries, not finite, are skipped) into a
    /// `width × height` depth map whose pixel side is `1 / scale` image pixels. The
    /// caller has checked the size against the allocation bound.
    pub fn render(
        view: &'v AcquisitionView<'a>,
        triangles: &[Option<[Point3<f64>; 3]>],
        (width, height): (usize, usize),
        scale: f64,
    ) -> Self {
        let mut out = Self {
            view,
            centre: view.centre(),
            max_r2: view.camera.max_radius_squared(),
            map: DepthMap {
                width,
                height,
                scale,
                depth: vec![f32::INFINITY; width.saturating_mul(height)],
            },
        };
        for corners in triangles.iter().flatten() {
            out.draw(corners);
        }
        out
    }

    /// A world point's image pixel and depth along the optical axis; `None` behind
    /// the camera, outside the distortion model's domain or not finite.
    pub fn project(&self, world: &Point3<f64>) -> Option<(Vector2<f64>, f64)> {
        let p = self.view.world_from_eo.inverse_transform_point(world);
        let pixel = self
            .view
            .camera
            .project_with_domain(&p.coords, self.max_r2)
            .ok()?;
        Some((pixel, p.z))
    }

    /// Whether nothing lies in front of a point at `depth` whose surface's depth
    /// changes by `gradient` per image pixel (x, y), at its depth-map pixel and the
    /// four neighbours: at each, the map must be no nearer than the point's own plane
    /// there, less `tolerance`. A neighbourhood, as the paper checks, so a point just
    /// behind an occluder's silhouette is not taken as seen through a sampling error;
    /// the plane, so a slanted surface does not hide itself. `None` when the pixel is
    /// off the map.
    pub fn clear_around(
        &self,
        pixel: &Vector2<f64>,
        depth: f64,
        gradient: [f64; 2],
        tolerance: f64,
    ) -> Option<bool> {
        let m = &self.map;
        let (fx, fy) = m.to_map(pixel);
        let (x, y) = (fx.round(), fy.round());
        if !(x >= 0.0 && y >= 0.0 && x < m.width as f64 && y < m.height as f64) {
            return None;
        }
        let (x, y) = (x as usize, y as usize);
        // Image pixels per depth-map pixel turn the gradient into the map's.
        let per_map_px = 1.0 / m.scale;
        let around = [(0i64, 0i64), (-1, 0), (1, 0), (0, -1), (0, 1)];
        let mut clear = true;
        for (dx, dy) in around {
            let (Some(nx), Some(ny)) = (
                x.checked_add_signed(dx as isize),
                y.checked_add_signed(dy as isize),
            ) else {
                continue;
            };
            let Some(map) = m.at(nx, ny) else {
                continue;
            };
            let offset = [nx as f64 - fx, ny as f64 - fy];
            let own = depth + per_map_px * (gradient[0] * offset[0] + gradient[1] * offset[1]);
            // Guard: a non-finite plane (an edge-on triangle) checks the pixel alone.
            let own = if own.is_finite() { own } else { depth };
            if f64::from(map) < own - tolerance {
                clear = false;
                break;
            }
        }
        Some(clear)
    }

    /// Pixels the depth map holds.
    pub fn pixels(&self) -> usize {
        self.map.depth.len()
    }

    /// Clips one triangle to the near plane in the optical frame, projects what is
    /// left and rasterises it (one or two triangles). A corner outside the distortion
    /// model's domain drops the triangle: its image is undefined there.
    fn draw(&mut self, corners: &[Point3<f64>; 3]) {
        let eo = corners.map(|c| self.view.world_from_eo.inverse_transform_point(&c).coords);
        let Some((polygon, len)) = clip_near(&eo) else {
            return;
        };
        let mut projected = [(Vector2::zeros(), 0.0); 4];
        for (slot, p) in projected.iter_mut().zip(&polygon[..len]) {
            let Ok(pixel) = self.view.camera.project_with_domain(p, self.max_r2) else {
                return;
            };
            let (x, y) = self.map.to_map(&pixel);
            *slot = (Vector2::new(x, y), p.z);
        }
        for k in 1..len.saturating_sub(1) {
            self.map
                .rasterise([projected[0], projected[k], projected[k + 1]]);
        }
    }
}

/// The part of a triangle (optical frame) at depth `NEAR_M` or more, as a polygon of
/// at most four corners (Sutherland–Hodgman against one plane); `None` when nothing
/// is left.
fn clip_near(tri: &[Vector3<f64>; 3]) -> Option<([Vector3<f64>; 4], usize)> {
    let mut out = [Vector3::zeros(); 4];
    let mut len = 0;
    for k in 0..3 {
        let (a, b) = (tri[k], tri[(k + 1) % 3]);
        let (a_in, b_in) = (a.z >= NEAR_M, b.z >= NEAR_M);
        if a_in {
            *out.get_mut(len)? = a;
            len += 1;
        }
        if a_in != b_in {
            // Guard: a_in != b_in puts a.z and b.z on either side of NEAR_M, so the
            // denominator is not zero.
            let t = (NEAR_M - a.z) / (b.z - a.z);
            *out.get_mut(len)? = a + (b - a) * t;
            len += 1;
        }
    }
    (len >= 3).then_some((out, len))
}

/// A z-buffer over the image at `scale` of its resolution, row-major.
struct DepthMap {
    width: usize,
    height: usize,
    scale: f64,
    depth: Vec<f32>,
}

impl DepthMap {
    /// Image pixel (centres at integers, the image spanning `-0.5..size-0.5`) to
    /// depth-map coordinates (centres at integers likewise).
    fn to_map(&self, pixel: &Vector2<f64>) -> (f64, f64) {
        (
            (pixel.x + 0.5) * self.scale - 0.5,
            (pixel.y + 0.5) * self.scale - 0.5,
        )
    }

    fn at(&self, x: usize, y: usize) -> Option<f32> {
        if x >= self.width {
            return None;
        }
        self.depth
            .get(y.checked_mul(self.width)?.checked_add(x)?)
            .copied()
    }

    /// Writes the nearer depth at every pixel centre inside the triangle; depth is
    /// interpolated as 1/z, which is linear in the image (perspective-correct). Both
    /// windings are drawn: back faces occlude too.
    fn rasterise(&mut self, v: [(Vector2<f64>, f64); 3]) {
        let [(p0, z0), (p1, z1), (p2, z2)] = v;
        let area = edge(&p0, &p1, &p2);
        if !area.is_finite() || area.abs() < MIN_SCREEN_AREA {
            return;
        }
        let (max_x, max_y) = (self.width as f64 - 1.0, self.height as f64 - 1.0);
        let lo_x = p0.x.min(p1.x).min(p2.x).ceil().max(0.0);
        let hi_x = p0.x.max(p1.x).max(p2.x).floor().min(max_x);
        let lo_y = p0.y.min(p1.y).min(p2.y).ceil().max(0.0);
        let hi_y = p0.y.max(p1.y).max(p2.y).floor().min(max_y);
        // Guard: also false for NaN bounds.
        if !(lo_x <= hi_x && lo_y <= hi_y) {
            return;
        }
        // Clipping keeps every depth at NEAR_M or more: the inverses are finite.
        let inv = [1.0 / z0, 1.0 / z1, 1.0 / z2];
        for y in lo_y as usize..=hi_y as usize {
            let row = y * self.width;
            for x in lo_x as usize..=hi_x as usize {
                let p = Vector2::new(x as f64, y as f64);
                let b = [
                    edge(&p1, &p2, &p) / area,
                    edge(&p2, &p0, &p) / area,
                    edge(&p0, &p1, &p) / area,
                ];
                if b.iter().any(|w| *w < -EDGE_SLACK) {
                    continue;
                }
                let inv_z = b[0] * inv[0] + b[1] * inv[1] + b[2] * inv[2];
                if inv_z <= 0.0 {
                    continue;
                }
                let z = (1.0 / inv_z) as f32;
                if let Some(d) = self.depth.get_mut(row + x)
                    && z < *d
                {
                    *d = z;
                }
            }
        }
    }
}

/// Twice the signed area of the triangle `a, b, p` (the edge function of `a → b`).
fn edge(a: &Vector2<f64>, b: &Vector2<f64>, p: &Vector2<f64>) -> f64 {
    (b.x - a.x) * (p.y - a.y) - (b.y - a.y) * (p.x - a.x)
}
