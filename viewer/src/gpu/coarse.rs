//! A scan's coarse triangle list, for the interactive frame: where a 4 x 4 (else a
//! 2 x 2) block of lidar cells is wholly covered by usable triangles (no depth
//! discontinuity, no dropout), its triangles become two over the block's corners;
//! elsewhere the usable triangles stay. (Where blocks of different sizes meet, a
//! curved surface may show a crack a pixel wide: acceptable while the view moves.) On a software rasteriser a frame of many scans is bound by
//! its triangles, not its pixels, so a smaller picture alone does not make it cheap.

use texel::TexelScan;

use crate::reliability::triangle_drawn;

/// The coarse index list of `scan` (the usable triangles' where its grid is not
/// known). Every index names an existing vertex; triangles keep the usable ones'
/// winding (towards the acquisition centre).
pub(crate) fn coarse_indices(scan: &TexelScan) -> Vec<u32> {
    let n = scan.vertices.len() as u32;
    let usable: Vec<[u32; 3]> = scan
        .triangles
        .iter()
        .enumerate()
        .filter(|(t, tri)| triangle_drawn(scan, *t, false) && tri.iter().all(|&v| v < n))
        .map(|(_, tri)| *tri)
        .collect();
    let (gw, gh) = (scan.grid_width as usize, scan.grid_height as usize);
    let cells = gw.checked_mul(gh).unwrap_or(0);
    let pixel_of = |v: u32| -> Option<(usize, usize)> {
        let p = *scan.vertex_pixel.get(v as usize)? as usize;
        (p < cells).then(|| (p % gw, p / gw))
    };
    if cells == 0 || scan.pixel_vertex.len() != cells || gw < 3 || gh < 3 {
        return usable.into_iter().flatten().collect();
    }
    // Each usable triangle's cell (its pixels' smallest x and y) when it lies within
    // one cell; the usable triangles per cell; the winding in pixel space.
    let mut cell_of = Vec::with_capacity(usable.len());
    let mut per_cell = vec![0u8; cells];
    let mut winding = 0i64;
    for tri in &usable {
        let px: Option<Vec<(usize, usize)>> = tri.iter().map(|&v| pixel_of(v)).collect();
        let cell = px.and_then(|px| {
            let (x0, y0) = (px.iter().map(|p| p.0).min()?, px.iter().map(|p| p.1).min()?);
            let (x1, y1) = (px.iter().map(|p| p.0).max()?, px.iter().map(|p| p.1).max()?);
            if winding == 0 {
                winding = cross(px[0], px[1], px[2]).signum();
            }
            (x1 - x0 <= 1 && y1 - y0 <= 1).then_some(y0 * gw + x0)
        });
        if let Some(c) = cell {
            per_cell[c] = per_cell[c].saturating_add(1);
        }
        cell_of.push(cell);
    }
    if winding == 0 {
        return usable.into_iter().flatten().collect();
    }
    let mut replaced = vec![false; cells];
    let mut out = Vec::with_capacity(usable.len() * 3);
    // Blocks of 4 x 4 cells first, then of 2 x 2 among what is left.
    for size in [4usize, 2] {
        for y in (0..gh.saturating_sub(size)).step_by(size) {
            for x in (0..gw.saturating_sub(size)).step_by(size) {
                let block = (y..y + size).flat_map(|by| (x..x + size).map(move |bx| by * gw + bx));
                if !block.clone().all(|c| per_cell[c] >= 2 && !replaced[c]) {
                    continue;
                }
                let corner = |cx: usize, cy: usize| scan.pixel_vertex[cy * gw + cx];
                let (a, b, c, d) = (
                    corner(x, y),
                    corner(x + size, y),
                    corner(x, y + size),
                    corner(x + size, y + size),
                );
                if [a, b, c, d].iter().any(|&v| v >= n) {
                    continue;
                }
                for cell in block {
                    replaced[cell] = true;
                }
                // (a, b, c) and (b, d, c) turn positively in pixel space.
                if winding > 0 {
                    out.extend_from_slice(&[a, b, c, b, d, c]);
                } else {
                    out.extend_from_slice(&[a, c, b, b, c, d]);
                }
            }
        }
    }
    for (tri, cell) in usable.iter().zip(&cell_of) {
        if !cell.is_some_and(|c| replaced[c]) {
            out.extend_from_slice(tri);
        }
    }
    out
}

/// The z of the 2-D cross product of `q - p` and `r - p` (pixel coordinates).
fn cross(p: (usize, usize), q: (usize, usize), r: (usize, usize)) -> i64 {
    let d =
        |a: (usize, usize), b: (usize, usize)| (b.0 as i64 - a.0 as i64, b.1 as i64 - a.1 as i64);
    let (u, v) = (d(p, q), d(p, r));
    u.0 * v.1 - u.1 * v.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenes;

    #[test]
    fn a_smooth_scan_keeps_few_of_its_triangles_wound_alike() {
        let sensor = scenes::test_sensor();
        let model = scenes::model_of(
            &scenes::box_scene(),
            &sensor,
            &scenes::box_scene_poses(),
            &texel::Pose::identity(),
        );
        for (_, scan) in model.resident() {
            let usable: usize = (0..scan.triangles.len())
                .filter(|&t| triangle_drawn(scan, t, false))
                .count();
            let coarse = coarse_indices(scan);
            assert_eq!(coarse.len() % 3, 0);
            let n = scan.vertices.len() as u32;
            assert!(coarse.iter().all(|&v| v < n));
            let triangles = coarse.len() / 3;
            assert!(
                triangles * 4 < usable && triangles * 40 > usable,
                "{triangles} coarse of {usable} usable"
            );
            // Every triangle faces the acquisition centre, as fusion winds them.
            let cop = glam::DVec3::from_array(scan.cop_m);
            let at = |v: u32| glam::DVec3::from_array(scan.vertices[v as usize].map(f64::from));
            let facing = coarse
                .chunks_exact(3)
                .filter(|t| {
                    let (a, b, c) = (at(t[0]), at(t[1]), at(t[2]));
                    (b - a).cross(c - a).dot(cop - a) > 0.0
                })
                .count();
            assert!(
                facing * 100 >= triangles * 99,
                "{facing} of {triangles} face the COP"
            );
        }
    }
}
