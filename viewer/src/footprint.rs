//! Where on screen a scan can draw: boxes around its vertices, one per tile of its
//! lidar grid, and the pixel rectangle they project to in a view. The rectangle is
//! conservative (every fragment of the scan falls inside it), so the k-buffer can
//! clear, draw and merge a scan's layer there alone instead of over the whole target.

use glam::{DMat4, DVec3};
use texel::TexelScan;

use crate::camera::VirtualCamera;

/// Tiles per side of the lidar grid: 64 boxes per scan. Finer tiles give tighter
/// rectangles (a tile box spans the depth steps inside it) at more corners to project.
pub const TILES_PER_SIDE: u32 = 8;

/// Pixels added around a projected rectangle: the GPU projects in f32 and samples
/// pixel centres, the CPU here in f64.
const MARGIN_PX: f64 = 2.0;

/// A rectangle of pixels, `x..x + width` by `y..y + height`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PixelRect {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

impl PixelRect {
    /// The whole `width` x `height` target.
    pub fn full(width: u32, height: u32) -> Self {
        Self {
            x: 0,
            y: 0,
            width,
            height,
        }
    }

    pub fn area(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height)
    }

    /// The smallest rectangle holding both.
    pub fn union(&self, other: &Self) -> Self {
        let x0 = self.x.min(other.x);
        let y0 = self.y.min(other.y);
        let x1 = (self.x + self.width).max(other.x + other.width);
        let y1 = (self.y + self.height).max(other.y + other.height);
        Self {
            x: x0,
            y: y0,
            width: x1 - x0,
            height: y1 - y0,
        }
    }

    /// The centre, in pixels.
    pub fn centre(&self) -> (u32, u32) {
        (self.x + self.width / 2, self.y + self.height / 2)
    }
}

/// Boxes (scan frame, min and max corner) that together hold every vertex of a scan.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Footprint {
    boxes: Vec<[DVec3; 2]>,
}

impl Footprint {
    /// One box per tile of the lidar grid that holds vertices (tiles by each vertex's
    /// lidar pixel); one box around all vertices when the grid does not describe them.
    pub fn of(scan: &TexelScan) -> Self {
        let (gw, gh) = (scan.grid_width, scan.grid_height);
        let gridded = gw > 0
            && gh > 0
            && scan.vertex_pixel.len() == scan.vertices.len()
            && scan
                .vertex_pixel
                .iter()
                .all(|&p| u64::from(p) < u64::from(gw) * u64::from(gh));
        let tile_w = gw.div_ceil(TILES_PER_SIDE).max(1);
        let tile_h = gh.div_ceil(TILES_PER_SIDE).max(1);
        let tiles = if gridded {
            (TILES_PER_SIDE * TILES_PER_SIDE) as usize
        } else {
            1
        };
        let mut boxes: Vec<Option<[DVec3; 2]>> = vec![None; tiles];
        for (i, v) in scan.vertices.iter().enumerate() {
            let p = DVec3::from_array(v.map(f64::from));
            if !p.is_finite() {
                continue;
            }
            let tile = match scan.vertex_pixel.get(i) {
                Some(&pixel) if gridded => {
                    let (col, row) = (pixel % gw, pixel / gw);
                    ((row / tile_h).min(TILES_PER_SIDE - 1) * TILES_PER_SIDE
                        + (col / tile_w).min(TILES_PER_SIDE - 1)) as usize
                }
                _ => 0,
            };
            let b = boxes[tile].get_or_insert([p, p]);
            b[0] = b[0].min(p);
            b[1] = b[1].max(p);
        }
        Self {
            boxes: boxes.into_iter().flatten().collect(),
        }
    }

    /// The pixels of `camera`'s target that the scan can draw, with the scan placed by
    /// `view_from_scan`: `None` when it draws none (every box behind the near plane or
    /// off the target); the whole target when a box straddles the near plane (its
    /// projection is unbounded there).
    pub fn screen_rect(&self, view_from_scan: &DMat4, camera: &VirtualCamera) -> Option<PixelRect> {
        let (w, h) = (f64::from(camera.width), f64::from(camera.height));
        let full = PixelRect::full(camera.width, camera.height);
        let f = camera.focal_px();
        let (mut lo, mut hi) = (
            [f64::INFINITY, f64::INFINITY],
            [f64::NEG_INFINITY, f64::NEG_INFINITY],
        );
        for b in &self.boxes {
            // On the stack: this runs for every box of every visible scan each frame.
            let corners: [DVec3; 8] = std::array::from_fn(|i| {
                let pick = |bit: usize, axis: usize| b[usize::from(i & bit != 0)][axis];
                view_from_scan.transform_point3(DVec3::new(pick(1, 0), pick(2, 1), pick(4, 2)))
            });
            let in_front = corners.iter().filter(|c| c.z > camera.near_m).count();
            if in_front == 0 {
                continue;
            }
            if in_front < corners.len() {
                return Some(full);
            }
            for c in corners {
                let px = [w * 0.5 + f * c.x / c.z, h * 0.5 + f * c.y / c.z];
                if !(px[0].is_finite() && px[1].is_finite()) {
                    return Some(full);
                }
                for a in 0..2 {
                    lo[a] = lo[a].min(px[a]);
                    hi[a] = hi[a].max(px[a]);
                }
            }
        }
        // Pixels whose centres can fall inside: [floor(lo), ceil(hi)), widened.
        let x0 = (lo[0] - MARGIN_PX).floor().max(0.0);
        let y0 = (lo[1] - MARGIN_PX).floor().max(0.0);
        let x1 = (hi[0] + MARGIN_PX).ceil().min(w);
        let y1 = (hi[1] + MARGIN_PX).ceil().min(h);
        if !(x0 < x1 && y0 < y1) {
            return None;
        }
        // Within [0, target size] here, so the casts are exact.
        Some(PixelRect {
            x: x0 as u32,
            y: y0 as u32,
            width: (x1 - x0) as u32,
            height: (y1 - y0) as u32,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenes;
    use proptest::prelude::*;
    use texel::pose::pose_from_parts;

    fn camera(world_from_eo: texel::Pose) -> VirtualCamera {
        VirtualCamera::new(world_from_eo, 60.0, 320, 240).unwrap()
    }

    /// Every vertex of the scan projects inside its rectangle.
    fn holds_every_vertex(scan: &TexelScan, cam: &VirtualCamera, world_from_scan: &texel::Pose) {
        let view_from_scan = crate::gpu::pose_relative(&cam.view_from_world(), world_from_scan);
        let rect = Footprint::of(scan).screen_rect(&view_from_scan, cam);
        for v in &scan.vertices {
            let p = view_from_scan.transform_point3(DVec3::from_array(v.map(f64::from)));
            let Some(px) = cam.project_view(&nalgebra::Vector3::new(p.x, p.y, p.z)) else {
                continue;
            };
            if p.z <= cam.near_m
                || px[0] < 0.0
                || px[1] < 0.0
                || px[0] >= f64::from(cam.width)
                || px[1] >= f64::from(cam.height)
            {
                continue;
            }
            let r = rect.expect("a vertex on screen, so the scan draws something");
            assert!(
                px[0] >= f64::from(r.x)
                    && px[0] <= f64::from(r.x + r.width)
                    && px[1] >= f64::from(r.y)
                    && px[1] <= f64::from(r.y + r.height),
                "vertex at {px:?} outside {r:?}"
            );
        }
    }

    #[test]
    fn a_wall_seen_from_aside_covers_part_of_the_screen() {
        let sensor = scenes::sensor(64, 48, 320, 240);
        let model = scenes::corridor(&sensor, 10);
        let (listed, scan) = model.resident().next().unwrap();
        // Back along the corridor, looking down it: the first wall panel is small.
        let cam = camera(scenes::look_at([4.5, 0.0, -6.0], [4.5, 0.0, 5.05]));
        let view_from_scan =
            crate::gpu::pose_relative(&cam.view_from_world(), &listed.world_from_scan);
        let rect = Footprint::of(scan)
            .screen_rect(&view_from_scan, &cam)
            .unwrap();
        assert!(
            rect.area() < PixelRect::full(320, 240).area() / 2,
            "{rect:?}"
        );
        holds_every_vertex(scan, &cam, &listed.world_from_scan);
    }

    #[test]
    fn a_scan_behind_the_camera_draws_nothing_and_one_across_the_near_plane_everywhere() {
        let sensor = scenes::sensor(64, 48, 320, 240);
        let model = scenes::corridor(&sensor, 1);
        let (listed, scan) = model.resident().next().unwrap();
        let fp = Footprint::of(scan);
        let ahead = camera(scenes::look_at([4.5, 0.0, -6.0], [4.5, 0.0, 5.05]));
        let behind = camera(scenes::look_at([0.0, 0.0, 40.0], [0.0, 0.0, 80.0]));
        let rel = |cam: &VirtualCamera| {
            crate::gpu::pose_relative(&cam.view_from_world(), &listed.world_from_scan)
        };
        assert!(fp.screen_rect(&rel(&ahead), &ahead).is_some());
        assert_eq!(fp.screen_rect(&rel(&behind), &behind), None);
        // The camera inside the scan's box: some box straddles the near plane.
        let (lo, hi) = scan.bounds().unwrap();
        let mid = listed
            .world_from_scan
            .transform_point(&nalgebra::Point3::new(
                f64::from(lo[0] + hi[0]) * 0.5,
                f64::from(lo[1] + hi[1]) * 0.5,
                f64::from(lo[2] + hi[2]) * 0.5,
            ));
        let inside = camera(pose_from_parts([mid.x, mid.y, mid.z], [0.0, 0.0, 0.0, 1.0]).unwrap());
        let r = fp.screen_rect(&rel(&inside), &inside);
        assert!(r.is_none() || r == Some(PixelRect::full(320, 240)), "{r:?}");
    }

    #[test]
    fn a_scan_without_a_grid_gets_one_box() {
        let sensor = scenes::sensor(16, 12, 64, 48);
        let model = scenes::corridor(&sensor, 1);
        let mut scan = texel::TexelScan::clone(model.resident().next().unwrap().1);
        scan.vertex_pixel.clear();
        assert_eq!(Footprint::of(&scan).boxes.len(), 1);
    }

    #[test]
    fn unions_hold_both() {
        let a = PixelRect {
            x: 10,
            y: 20,
            width: 5,
            height: 5,
        };
        let b = PixelRect {
            x: 2,
            y: 30,
            width: 4,
            height: 1,
        };
        let u = a.union(&b);
        assert_eq!(
            u,
            PixelRect {
                x: 2,
                y: 20,
                width: 13,
                height: 11
            }
        );
        assert_eq!(u.area(), 143);
    }

    proptest! {
        /// From any pose around the corridor, every on-screen vertex of every scan lies
        /// in the scan's rectangle.
        #[test]
        fn rectangles_hold_every_vertex(
            x in -2.0f64..10.0,
            y in -3.0f64..3.0,
            z in -8.0f64..4.0,
            tx in 0.0f64..9.0,
            ty in -1.0f64..1.0,
        ) {
            let sensor = scenes::sensor(32, 24, 64, 48);
            let model = scenes::corridor(&sensor, 10);
            let target = [tx, ty, 5.05];
            prop_assume!((DVec3::from_array(target) - DVec3::new(x, y, z)).length() > 0.5);
            let cam = camera(scenes::look_at([x, y, z], target));
            for (listed, scan) in model.resident() {
                holds_every_vertex(scan, &cam, &listed.world_from_scan);
            }
        }
    }
}
