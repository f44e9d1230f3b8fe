//! Grid growing: from a seed corner and two neighbours along board edges, corners are
//! added one grid step at a time where a candidate lies near the extrapolated
//! position *and* the segment to it runs along a dark/light edge. The grown grid is
//! then given the board's indices (axes by the unequal corner counts, handedness by
//! the image, the 180° turn by which squares are dark).

use std::collections::{HashMap, VecDeque};

use nalgebra::Vector2;

use super::saddle::Candidate;
use crate::gray::GrayImage;

/// A grown grid: integer grid coordinates of candidate indices.
#[derive(Debug, Clone, Default)]
pub struct Grown {
    pub cells: HashMap<(i32, i32), usize>,
}

impl Grown {
    pub fn extent(&self) -> (i32, i32, i32, i32) {
        let mut e = (i32::MAX, i32::MAX, i32::MIN, i32::MIN);
        for &(i, j) in self.cells.keys() {
            e.0 = e.0.min(i);
            e.1 = e.1.min(j);
            e.2 = e.2.max(i);
            e.3 = e.3.max(j);
        }
        e
    }

    pub fn size(&self) -> (i32, i32) {
        if self.cells.is_empty() {
            return (0, 0);
        }
        let e = self.extent();
        (e.2 - e.0 + 1, e.3 - e.1 + 1)
    }
}

/// True when the segment `p → q` runs along an edge between a dark and a light
/// square: the two sides of it differ by at least `min_step`.
pub fn is_edge(image: &GrayImage, p: Vector2<f64>, q: Vector2<f64>, min_step: f32) -> bool {
    let d = q - p;
    let len = d.norm();
    if !(len > 1.0e-6) {
        return false;
    }
    let perp = Vector2::new(-d.y, d.x) / len * (0.25 * len);
    let mut agree = 0;
    let mut first_sign = 0.0f32;
    for (k, t) in [0.35, 0.5, 0.65].into_iter().enumerate() {
        let m = p + d * t;
        let diff =
            image.sample(m.x + perp.x, m.y + perp.y) - image.sample(m.x - perp.x, m.y - perp.y);
        if diff.abs() < min_step {
            return false;
        }
        if k == 0 {
            first_sign = diff.signum();
        }
        if diff.signum() == first_sign {
            agree += 1;
        }
    }
    agree == 3
}

/// Grows a grid from candidate `seed`. `None` when the seed has no two edge
/// neighbours at right-ish angles.
pub fn grow(image: &GrayImage, cands: &[Candidate], seed: usize) -> Option<Grown> {
    let c = cands.get(seed)?;
    let step_of = |a: &Candidate, b: &Candidate| 0.3 * a.contrast.min(b.contrast);
    // Nearest neighbours of the seed.
    let mut near: Vec<(f64, usize)> = cands
        .iter()
        .enumerate()
        .filter(|&(k, _)| k != seed)
        .map(|(k, o)| ((o.p - c.p).norm(), k))
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0));
    near.truncate(8);
    let edge_near: Vec<(f64, usize)> = near
        .iter()
        .copied()
        .filter(|&(_, k)| is_edge(image, c.p, cands[k].p, step_of(c, &cands[k])))
        .collect();
    let &(da, a) = edge_near.first()?;
    let ua = (cands[a].p - c.p) / da;
    let b = edge_near.iter().skip(1).find_map(|&(db, b)| {
        let ub = (cands[b].p - c.p) / db;
        let ratio = db / da;
        (ua.dot(&ub).abs() < 0.55 && (0.5..=2.0).contains(&ratio)).then_some(b)
    })?;
    let mut cells = HashMap::new();
    let mut used = vec![false; cands.len()];
    for (cell, k) in [((0, 0), seed), ((1, 0), a), ((0, 1), b)] {
        cells.insert(cell, k);
        used[k] = true;
    }
    let basis = [cands[a].p - c.p, cands[b].p - c.p];
    let mut queue: VecDeque<(i32, i32)> = [(0, 0), (1, 0), (0, 1)].into_iter().collect();
    let dirs = [(1, 0), (-1, 0), (0, 1), (0, -1)];
    while let Some((i, j)) = queue.pop_front() {
        let Some(&here) = cells.get(&(i, j)) else {
            continue;
        };
        let p = cands[here].p;
        for (di, dj) in dirs {
            let target = (i + di, j + dj);
            if cells.contains_key(&target) {
                continue;
            }
            let Some(pred) = predict(&cells, cands, (i, j), (di, dj), basis) else {
                continue;
            };
            let step = (pred - p).norm();
            let radius = 0.3 * step;
            let best = cands
                .iter()
                .enumerate()
                .filter(|&(k, o)| !used[k] && (o.p - pred).norm() < radius)
                .min_by(|x, y| (x.1.p - pred).norm().total_cmp(&(y.1.p - pred).norm()));
            if let Some((k, o)) = best
                && is_edge(image, p, o.p, step_of(&cands[here], o))
            {
                cells.insert(target, k);
                used[k] = true;
                queue.push_back(target);
            }
        }
        // A runaway grid (clutter that looks like a board) stops here.
        if cells.len() > 4096 {
            break;
        }
    }
    Some(Grown { cells })
}

/// Predicted image position of `from + dir`: linear extrapolation along the row or
/// column when the point behind is known, else the step of a parallel neighbour, else
/// the seed's basis.
fn predict(
    cells: &HashMap<(i32, i32), usize>,
    cands: &[Candidate],
    from: (i32, i32),
    dir: (i32, i32),
    basis: [Vector2<f64>; 2],
) -> Option<Vector2<f64>> {
    let p = cands[*cells.get(&from)?].p;
    if let Some(&back) = cells.get(&(from.0 - dir.0, from.1 - dir.1)) {
        return Some(2.0 * p - cands[back].p);
    }
    // A parallel step one row or column over.
    let sides = if dir.0 != 0 {
        [(0, 1), (0, -1)]
    } else {
        [(1, 0), (-1, 0)]
    };
    for s in sides {
        let a = (from.0 + s.0, from.1 + s.1);
        let b = (a.0 + dir.0, a.1 + dir.1);
        if let (Some(&ka), Some(&kb)) = (cells.get(&a), cells.get(&b)) {
            return Some(p + (cands[kb].p - cands[ka].p));
        }
    }
    let step = match dir {
        (1, 0) => basis[0],
        (-1, 0) => -basis[0],
        (0, 1) => basis[1],
        _ => -basis[1],
    };
    Some(p + step)
}

/// Board indices for a grown grid of exactly `nx x ny` extent (either way round):
/// `Some(map from (i, j) to candidate)` with the board's axes, handedness and turn.
pub fn order(
    image: &GrayImage,
    cands: &[Candidate],
    grown: &Grown,
    nx: i32,
    ny: i32,
) -> Option<HashMap<(i32, i32), usize>> {
    let (i0, j0, _, _) = grown.extent();
    let (sx, sy) = grown.size();
    let swap = if (sx, sy) == (nx, ny) {
        false
    } else if (sx, sy) == (ny, nx) {
        true
    } else {
        return None;
    };
    let mut cells: HashMap<(i32, i32), usize> = grown
        .cells
        .iter()
        .map(|(&(i, j), &k)| {
            let (i, j) = (i - i0, j - j0);
            (if swap { (j, i) } else { (i, j) }, k)
        })
        .collect();
    // Handedness: with image y down, a board whose z points away from the camera has
    // x × y > 0 in image coordinates.
    let mut cross = 0.0;
    for (&(i, j), &k) in &cells {
        if let (Some(&kx), Some(&ky)) = (cells.get(&(i + 1, j)), cells.get(&(i, j + 1))) {
            let ex = cands[kx].p - cands[k].p;
            let ey = cands[ky].p - cands[k].p;
            cross += ex.x * ey.y - ex.y * ey.x;
        }
    }
    if cross == 0.0 {
        return None;
    }
    if cross < 0.0 {
        cells = cells
            .into_iter()
            .map(|((i, j), k)| ((i, ny - 1 - j), k))
            .collect();
    }
    // The turn: square (sx, sy) between inner corners (sx-1, sy-1) and (sx, sy) is dark
    // when sx + sy is even.
    let (mut even, mut odd, mut n_even, mut n_odd) = (0.0f64, 0.0f64, 0usize, 0usize);
    for (&(i, j), &k) in &cells {
        let Some(&kd) = cells.get(&(i + 1, j + 1)) else {
            continue;
        };
        let centre = 0.5 * (cands[k].p + cands[kd].p);
        let v = f64::from(image.sample(centre.x, centre.y));
        if (i + 1 + j + 1) % 2 == 0 {
            even += v;
            n_even += 1;
        } else {
            odd += v;
            n_odd += 1;
        }
    }
    if n_even == 0 || n_odd == 0 {
        return None;
    }
    if even / n_even as f64 > odd / n_odd as f64 {
        cells = cells
            .into_iter()
            .map(|((i, j), k)| ((nx - 1 - i, ny - 1 - j), k))
            .collect();
    }
    Some(cells)
}
