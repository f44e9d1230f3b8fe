//! Points (Sec. 3), one row of lidar pixels at a time: every pixel of the row is
//! placed and projected by one branch-free loop over arrays (which the compiler
//! vectorises), then the row's returns are appended to the scan's vertex arrays run
//! by run (slice copies). The row stays behind, in the same layout, for the mesh
//! between it and the next.

use crate::frames::{RangeFrame, is_return};
use crate::fusion_tables::FusionTables;
use crate::scan::NO_VERTEX;

use super::runs_of_true;

/// One row of lidar pixels after placement.
#[derive(Debug, Clone, Default)]
pub(super) struct Row {
    /// Row-major index of the row's first pixel.
    pub first_pixel: usize,
    /// EO-frame point of each pixel as the scan stores it (f32), also as one array
    /// per coordinate for the mesh's vector loops; meaningless where the pixel has no
    /// vertex.
    pub point: Vec<[f32; 3]>,
    pub x: Vec<f32>,
    pub y: Vec<f32>,
    pub z: Vec<f32>,
    /// Texture coordinate, `[0, 0]` where the point is not on the EO image.
    pub tex: Vec<[f32; 2]>,
    /// The pixel has a return along a valid ray: it gets a vertex.
    pub placed: Vec<bool>,
    /// Placed, and its point projects onto the EO image.
    pub textured: Vec<bool>,
    /// The pixel's vertex where it may be used by the mesh (placed and textured),
    /// else [`NO_VERTEX`].
    pub usable: Vec<u32>,
}

impl Row {
    pub fn new(width: usize) -> Self {
        Self {
            first_pixel: 0,
            point: vec![[0.0; 3]; width],
            x: vec![0.0; width],
            y: vec![0.0; width],
            z: vec![0.0; width],
            tex: vec![[0.0; 2]; width],
            placed: vec![false; width],
            textured: vec![false; width],
            usable: vec![NO_VERTEX; width],
        }
    }

    pub fn width(&self) -> usize {
        self.x.len()
    }

    /// Places and projects every pixel of row `v`: the EO-frame point
    /// `ray · (r - range_bias_m) + t`
    /// (the lidar ray already turned into the EO frame), then its texture coordinate
    /// through the EO model, distortion included.
    #[inline(always)]
    pub fn place(
        &mut self,
        v: usize,
        range: &RangeFrame,
        tables: &FusionTables,
        range_bias_m: f64,
    ) {
        let n = self.width();
        let first = v * n;
        self.first_pixel = first;
        let pixels = first..first + n;
        let (Some(ranges), Some(rx), Some(ry), Some(rz), Some(valid)) = (
            range.ranges_m.get(pixels.clone()),
            tables.ray_x.get(pixels.clone()),
            tables.ray_y.get(pixels.clone()),
            tables.ray_z.get(pixels.clone()),
            tables.ray_valid.get(pixels),
        ) else {
            return;
        };
        let (x, y, z) = (&mut self.x[..n], &mut self.y[..n], &mut self.z[..n]);
        let (point, tex) = (&mut self.point[..n], &mut self.tex[..n]);
        let (placed, textured) = (&mut self.placed[..n], &mut self.textured[..n]);
        let t = tables.translation;
        let bias = if range_bias_m.is_finite() {
            range_bias_m
        } else {
            0.0
        };
        let projection = &tables.projection;
        for i in 0..n {
            // The measured range less the sensor's bias; a bias as large as the range
            // leaves no point in front of the lidar (and a NaN fails the comparison).
            let r = f64::from(ranges[i]) - bias;
            let p = [rx[i] * r + t[0], ry[i] * r + t[1], rz[i] * r + t[2]];
            let (uv, on_image) = projection.project(p);
            let has_vertex = valid[i] & is_return(ranges[i]) & (r > 0.0);
            let stored = p.map(|c| c as f32);
            (x[i], y[i], z[i]) = (stored[0], stored[1], stored[2]);
            point[i] = stored;
            placed[i] = has_vertex;
            textured[i] = has_vertex & on_image;
            tex[i] = if on_image { uv } else { [0.0; 2] };
        }
    }
}

/// The scan's per-vertex arrays, filled row by row.
#[derive(Debug, Default)]
pub(super) struct Points {
    pub vertices: Vec<[f32; 3]>,
    pub tex_coords: Vec<[f32; 2]>,
    pub vertex_textured: Vec<bool>,
    pub vertex_pixel: Vec<u32>,
    pub pixel_vertex: Vec<u32>,
}

impl Points {
    /// Room for exactly `vertices` vertices of a grid of `pixels` pixels.
    pub fn with_capacity(vertices: usize, pixels: usize) -> Self {
        Self {
            vertices: Vec::with_capacity(vertices),
            tex_coords: Vec::with_capacity(vertices),
            vertex_textured: Vec::with_capacity(vertices),
            vertex_pixel: Vec::with_capacity(vertices),
            pixel_vertex: Vec::with_capacity(pixels),
        }
    }

    /// Appends the vertices of a placed row (each run of placed pixels as slice
    /// copies) and numbers the row's usable ones.
    #[inline(always)]
    pub fn append(&mut self, row: &mut Row) {
        let n = row.width();
        let first_vertex = self.vertices.len() as u32;
        let mut next = first_vertex;
        self.pixel_vertex
            .extend(row.placed[..n].iter().map(|&placed| {
                let vertex = if placed { next } else { NO_VERTEX };
                next += u32::from(placed);
                vertex
            }));
        let numbers = &self.pixel_vertex[self.pixel_vertex.len() - n..];
        for ((usable, &vertex), &textured) in row.usable[..n]
            .iter_mut()
            .zip(numbers)
            .zip(&row.textured[..n])
        {
            *usable = if textured { vertex } else { NO_VERTEX };
        }
        for run in runs_of_true(&row.placed[..n]) {
            self.vertices.extend_from_slice(&row.point[run.clone()]);
            self.tex_coords.extend_from_slice(&row.tex[run.clone()]);
            self.vertex_textured
                .extend_from_slice(&row.textured[run.clone()]);
            let pixels = row.first_pixel + run.start..row.first_pixel + run.end;
            self.vertex_pixel.extend(pixels.map(|p| p as u32));
        }
    }
}
