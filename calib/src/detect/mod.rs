//! Finding the checkerboard in an image from its pixels alone: X-corner candidates
//! ([`saddle`]), grid growing and board indexing ([`grid`]), sub-pixel corners.
//! Works on EO images and on lidar intensity images (smaller scale parameters).

pub mod grid;
pub mod saddle;

use nalgebra::Vector2;
use thiserror::Error;

use crate::config::TargetConfig;
use crate::gray::GrayImage;

/// Largest move of a corner when it is refined again with the square-sized window.
const MAX_RESCALED_SHIFT_PX: f64 = 0.25;

/// Scale parameters of the detector.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DetectParams {
    /// Gaussian smoothing before the saddle response, pixels.
    pub blur_sigma_px: f64,
    /// Radius of the ring test, pixels (about a third of the smallest square).
    pub ring_radius_px: f64,
    /// Half-size of the sub-pixel refinement window, pixels.
    pub half_window_px: usize,
    /// Fewest of the board's corners a detection may have (occlusion), as a fraction.
    pub min_fraction: f64,
    /// Seeds tried before giving up.
    pub max_seeds: usize,
}

impl DetectParams {
    /// Parameters for an EO image of this size.
    pub fn eo(width: usize, height: usize) -> Self {
        let side = width.min(height) as f64;
        let ring = (side / 110.0).clamp(2.5, 12.0);
        Self {
            blur_sigma_px: (ring * 0.3).max(0.7),
            ring_radius_px: ring,
            half_window_px: (ring.round() as usize).clamp(2, 10),
            min_fraction: 0.7,
            max_seeds: 25,
        }
    }

    /// Parameters for a low-resolution lidar intensity image (squares of a few pixels).
    pub fn lidar() -> Self {
        Self {
            blur_sigma_px: 0.6,
            ring_radius_px: 1.8,
            half_window_px: 2,
            min_fraction: 0.7,
            max_seeds: 25,
        }
    }
}

/// The board's inner corners found in one image.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardCorners {
    pub nx: usize,
    pub ny: usize,
    /// Corner `(i, j)` at index `j * nx + i`; `None` where it was not found.
    pub corners: Vec<Option<Vector2<f64>>>,
}

impl BoardCorners {
    pub fn found(&self) -> usize {
        self.corners.iter().filter(|c| c.is_some()).count()
    }

    /// `(i, j, pixel)` of every found corner.
    pub fn iter(&self) -> impl Iterator<Item = (usize, usize, Vector2<f64>)> + '_ {
        self.corners
            .iter()
            .enumerate()
            .filter_map(|(k, c)| c.map(|p| (k % self.nx, k / self.nx, p)))
    }

    pub fn get(&self, i: usize, j: usize) -> Option<Vector2<f64>> {
        if i >= self.nx || j >= self.ny {
            return None;
        }
        self.corners.get(j * self.nx + i).copied().flatten()
    }

    /// Median distance between neighbouring corners, pixels.
    pub fn spacing_px(&self) -> f64 {
        let mut d: Vec<f64> = Vec::new();
        for (i, j, p) in self.iter() {
            if let Some(q) = self.get(i + 1, j) {
                d.push((q - p).norm());
            }
            if let Some(q) = self.get(i, j + 1) {
                d.push((q - p).norm());
            }
        }
        if d.is_empty() {
            return 0.0;
        }
        let mid = d.len() / 2;
        d.select_nth_unstable_by(mid, f64::total_cmp);
        d[mid]
    }
}

/// Why an image gave no board.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum DetectFailure {
    #[error("no checkerboard corners in the image")]
    NoCorners,
    #[error(
        "no {nx}x{ny} corner grid: the largest grid found is {found_x}x{found_y} \
         (board partly outside the image or hidden?)"
    )]
    NoGrid {
        nx: usize,
        ny: usize,
        found_x: usize,
        found_y: usize,
    },
    #[error("only {found} of {total} corners found (board too occluded)")]
    TooFewCorners { found: usize, total: usize },
}

/// Finds the board of `target` in `image`.
pub fn detect_board(
    image: &GrayImage,
    target: &TargetConfig,
    params: &DetectParams,
) -> Result<BoardCorners, DetectFailure> {
    let (nx, ny) = (target.nx(), target.ny());
    // Step 1: X-corner candidates (saddle response, ring test, sub-pixel refinement).
    let b = image.blurred(params.blur_sigma_px);
    let (gx, gy) = saddle::gradients(&b);
    let cands = saddle::candidates(&b, &gx, &gy, params.ring_radius_px, params.half_window_px);
    if cands.len() < 4 {
        return Err(DetectFailure::NoCorners);
    }
    // Step 2: grow grids from the strongest seeds until one has the board's extent.
    let mut best = (0usize, 0usize);
    let mut best_found = 0usize;
    let mut tried_in_grids = vec![false; cands.len()];
    for seed in 0..cands.len().min(params.max_seeds.max(1) * 4) {
        if tried_in_grids[seed] {
            continue;
        }
        let Some(grown) = grid::grow(&b, &cands, seed) else {
            continue;
        };
        for &k in grown.cells.values() {
            tried_in_grids[k] = true;
        }
        let (sx, sy) = grown.size();
        let (sx, sy) = (sx.max(0) as usize, sy.max(0) as usize);
        if grown.cells.len() > best_found {
            best_found = grown.cells.len();
            best = (sx.max(sy), sx.min(sy));
        }
        // Step 3: board indices (axes, handedness, turn).
        let Some(cells) = grid::order(&b, &cands, &grown, nx as i32, ny as i32) else {
            continue;
        };
        let total = nx * ny;
        if (cells.len() as f64) < params.min_fraction * total as f64 {
            return Err(DetectFailure::TooFewCorners {
                found: cells.len(),
                total,
            });
        }
        let mut corners = vec![None; total];
        for ((i, j), k) in cells {
            if i >= 0 && j >= 0 && (i as usize) < nx && (j as usize) < ny {
                corners[j as usize * nx + i as usize] = Some(cands[k].p);
            }
        }
        let mut board = BoardCorners { nx, ny, corners };
        // Step 4: refine again with a window scaled to the squares (about a third of
        // a square): more gradient pixels, less noise, still inside the four squares.
        // A corner whose larger window takes in something else (an occluder's edge)
        // moves further than noise would move it, and keeps its first position.
        let window = (0.3 * board.spacing_px()).round().clamp(2.0, 12.0) as usize;
        if window > params.half_window_px {
            for c in board.corners.iter_mut().flatten() {
                if let Some(p) = saddle::refine(&gx, &gy, *c, window, MAX_RESCALED_SHIFT_PX) {
                    *c = p;
                }
            }
        }
        return Ok(board);
    }
    Err(DetectFailure::NoGrid {
        nx: nx.max(ny),
        ny: nx.min(ny),
        found_x: best.0,
        found_y: best.1,
    })
}
