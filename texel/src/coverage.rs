//! Scan coverage signatures and scan retirement: what surface a scan shows and how
//! reliably (a few hundred samples in the scan's own frame), and the incremental
//! index that retires scans whose every surface cell is offered at least as reliably
//! by scans the model keeps. `docs/model.md` ("Retirement") states the criterion.

pub mod links;
mod offers;
mod retirement;
mod shelf;

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::scan::{NO_VERTEX, TexelScan};

pub use retirement::{Changes, Retirement, RetirementCounts};
pub use shelf::{MemoryShelf, Shelf, ShelfError};

/// The most samples one signature holds, whatever the lidar grid: the stride grows
/// for grids so large that the configured one would exceed it.
pub const MAX_SAMPLES: usize = 1024;

/// Ranges below this (metres) are a centre of projection on the surface: such a
/// sample has no acquisition direction and is dropped.
pub const MIN_RANGE_M: f64 = 1.0e-6;

/// Parameters of the coverage signature and of the redundancy test.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CoverageConfig {
    /// Retire redundant scans at all; when false every scan is served.
    pub enabled: bool,
    /// Edge of the world surface cells, metres (clamped into [0.01, 100]).
    pub cell_m: f64,
    /// One sample per `sample_stride_px` x `sample_stride_px` block of lidar pixels
    /// (clamped into [1, 64]); 8 gives 256 samples (4 KiB) on a 128x128 grid.
    pub sample_stride_px: u32,
    /// Largest angle between two acquisition directions at a cell for one scan's
    /// offer to stand in for the other's, degrees (clamped into [0, 90]).
    pub angle_tolerance_deg: f64,
    /// Reliability a dominating offer may lack (normal accuracy x range factor
    /// against the dominated one), in [0, 1].
    pub reliability_margin: f64,
    /// The range confidence exponent the viewer renders with (`range_gamma`).
    pub range_gamma: f64,
    /// Served scans examined per cell when looking for a dominating offer: a bound
    /// on one test's work, set well above the served scans a cell of a session
    /// gathers (a lower one misses witnesses and serves scans that are redundant;
    /// docs/model.md, "The index and its bounded work").
    pub max_candidates_per_cell: usize,
    /// Examine a cell's served scans strongest offer first instead of in arrival
    /// order. It decides which witness is found first; it decides whether one is
    /// found only in cells with more served scans than `max_candidates_per_cell`
    /// (docs/model.md, "The index and its bounded work").
    pub strongest_candidates_first: bool,
    /// Redundancy tests per `add` / `revise` call; past it, the safe outcome is
    /// taken (a scan whose witness moved is served again, unexamined neighbours
    /// stay served).
    pub max_checks_per_call: usize,
}

impl Default for CoverageConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            cell_m: 1.0,
            sample_stride_px: 8,
            angle_tolerance_deg: 20.0,
            reliability_margin: 0.1,
            range_gamma: 1.0,
            max_candidates_per_cell: 1024,
            strongest_candidates_first: false,
            max_checks_per_call: 64,
        }
    }
}

impl CoverageConfig {
    /// `cell_m` made usable: finite, within [0.01, 100] m.
    pub fn cell_size_m(&self) -> f64 {
        if self.cell_m.is_finite() {
            self.cell_m.clamp(0.01, 100.0)
        } else {
            1.0
        }
    }

    /// `sample_stride_px` within [1, 64].
    pub fn stride_px(&self) -> u32 {
        self.sample_stride_px.clamp(1, 64)
    }

    /// Cosine of the angular tolerance (the tolerance clamped into [0, 90] degrees;
    /// not finite counts as 0).
    pub fn cos_tolerance(&self) -> f64 {
        let deg = if self.angle_tolerance_deg.is_finite() {
            self.angle_tolerance_deg.clamp(0.0, 90.0)
        } else {
            0.0
        };
        deg.to_radians().cos()
    }

    /// The reliability margin within [0, 1] (not finite counts as 0).
    pub fn margin(&self) -> f64 {
        if self.reliability_margin.is_finite() {
            self.reliability_margin.clamp(0.0, 1.0)
        } else {
            0.0
        }
    }

    /// The range exponent, > 0 and finite (else 1, as the viewer does).
    pub fn gamma(&self) -> f64 {
        if self.range_gamma.is_finite() && self.range_gamma > 0.0 {
            self.range_gamma
        } else {
            1.0
        }
    }
}

/// One sample of a scan's surface: a vertex in the scan frame and the normal
/// accuracy of the triangles around it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CoverageSample {
    pub point_m: [f32; 3],
    /// Mean normal accuracy of the usable triangles around the vertex, in (0, 1].
    pub normal_accuracy: f32,
}

/// What a scan shows: samples of its usable surface in the scan's own frame, and the
/// acquisition centre of projection they were seen from. A pose revision moves it
/// as a whole; nothing in it depends on where the scan is in the world.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ScanCoverage {
    pub cop_m: [f64; 3],
    pub samples: Vec<CoverageSample>,
}

impl ScanCoverage {
    /// The signature of `scan`: per block of lidar pixels, the vertex nearest the
    /// block's centre among those touched by a usable triangle (neither stretched
    /// nor degenerate) of positive normal accuracy. A scan without such triangles
    /// has no samples: it covers nothing.
    pub fn of(scan: &TexelScan, config: &CoverageConfig) -> Self {
        let cop_finite = scan.cop_m.iter().all(|c| c.is_finite());
        let width = scan.grid_width as usize;
        let height = scan.grid_height as usize;
        if !cop_finite || width == 0 || height == 0 {
            return Self {
                cop_m: if cop_finite { scan.cop_m } else { [0.0; 3] },
                samples: Vec::new(),
            };
        }
        let grid = BlockGrid::new(width, height, config.stride_px() as usize);
        let usable = usable_vertices(scan);
        let accuracy = block_accuracy(scan, &grid);
        let cop = Vector3::from(scan.cop_m);
        let mut samples = Vec::with_capacity(grid.count().min(MAX_SAMPLES));
        for b in 0..grid.count() {
            let Some(&(sum, n)) = accuracy.get(b) else {
                continue;
            };
            if n == 0 || sum <= 0.0 {
                continue;
            }
            if let Some(point_m) = block_point(scan, &usable, &cop, &grid.block(b))
                && samples.len() < MAX_SAMPLES
            {
                samples.push(CoverageSample {
                    point_m,
                    normal_accuracy: (sum / f64::from(n)) as f32,
                });
            }
        }
        Self {
            cop_m: scan.cop_m,
            samples,
        }
    }

    /// Bytes held on the heap.
    pub fn heap_bytes(&self) -> usize {
        self.samples.capacity() * std::mem::size_of::<CoverageSample>()
    }

    /// How much the scan shows, reliability-weighted: the sum of its samples' normal
    /// accuracies (each sample stands for the same share of the lidar grid). Orders
    /// scans "most reliable first"; 0 for a scan that covers nothing.
    pub fn score(&self) -> f64 {
        self.samples
            .iter()
            .map(|s| f64::from(s.normal_accuracy))
            .filter(|a| a.is_finite())
            .sum()
    }

    /// Whether the scan covers nothing (and so is always redundant).
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }
}

/// A rectangle of lidar pixels, `[x0, x1) x [y0, y1)`.
struct Block {
    x0: usize,
    y0: usize,
    x1: usize,
    y1: usize,
}

/// The lidar grid cut into square blocks of `stride` pixels, row-major.
struct BlockGrid {
    width: usize,
    height: usize,
    stride: usize,
    blocks_x: usize,
}

impl BlockGrid {
    /// The grid of blocks; the stride grows past the configured one when the grid
    /// would otherwise have more than [`MAX_SAMPLES`] blocks.
    fn new(width: usize, height: usize, configured: usize) -> Self {
        let mut stride = configured.max(1);
        while width.div_ceil(stride) * height.div_ceil(stride) > MAX_SAMPLES {
            stride += 1;
        }
        Self {
            width,
            height,
            stride,
            blocks_x: width.div_ceil(stride),
        }
    }

    fn count(&self) -> usize {
        self.blocks_x * self.height.div_ceil(self.stride)
    }

    /// The block of lidar pixel `pixel` (row-major), `None` outside the grid.
    fn of_pixel(&self, pixel: usize) -> Option<usize> {
        let (x, y) = (pixel % self.width, pixel / self.width);
        (y < self.height).then(|| (y / self.stride) * self.blocks_x + x / self.stride)
    }

    fn block(&self, b: usize) -> Block {
        let (bx, by) = (b % self.blocks_x, b / self.blocks_x);
        Block {
            x0: bx * self.stride,
            y0: by * self.stride,
            x1: ((bx + 1) * self.stride).min(self.width),
            y1: ((by + 1) * self.stride).min(self.height),
        }
    }
}

/// The block's point: the vertex nearest the block centre among those of a usable
/// triangle, at a positive distance from the centre of projection.
fn block_point(
    scan: &TexelScan,
    usable: &[bool],
    cop: &Vector3<f64>,
    block: &Block,
) -> Option<[f32; 3]> {
    let width = scan.grid_width as usize;
    // Twice the centre, so odd and even blocks stay in integers.
    let cx2 = block.x0 + block.x1 - 1;
    let cy2 = block.y0 + block.y1 - 1;
    let mut best: Option<(usize, [f32; 3])> = None;
    for y in block.y0..block.y1 {
        for x in block.x0..block.x1 {
            let Some(&v) = scan.pixel_vertex.get(y * width + x) else {
                continue;
            };
            if v == NO_VERTEX || !usable.get(v as usize).copied().unwrap_or(false) {
                continue;
            }
            let Some(&p) = scan.vertices.get(v as usize) else {
                continue;
            };
            let point = Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            if !p.iter().all(|c| c.is_finite()) || (cop - point).norm() < MIN_RANGE_M {
                continue;
            }
            let d = (2 * x).abs_diff(cx2).pow(2) + (2 * y).abs_diff(cy2).pow(2);
            if best.as_ref().is_none_or(|(bd, _)| d < *bd) {
                best = Some((d, p));
            }
        }
    }
    best.map(|(_, p)| p)
}

/// Whether each vertex belongs to a usable triangle (neither stretched nor
/// degenerate).
fn usable_vertices(scan: &TexelScan) -> Vec<bool> {
    let mut usable = vec![false; scan.vertices.len()];
    for (t, tri) in scan.triangles.iter().enumerate() {
        if !scan.triangle_flags.get(t).is_some_and(|f| f.is_usable()) {
            continue;
        }
        for &v in tri {
            if let Some(u) = usable.get_mut(v as usize) {
                *u = true;
            }
        }
    }
    usable
}

/// Per block: the sum and count of the normal accuracies of the usable triangles
/// whose first vertex lies in it. The block mean, not one triangle's, is the
/// sample's accuracy: single triangles carry the range noise of three returns.
fn block_accuracy(scan: &TexelScan, grid: &BlockGrid) -> Vec<(f64, u32)> {
    let mut sums = vec![(0.0f64, 0u32); grid.count()];
    for (t, tri) in scan.triangles.iter().enumerate() {
        if !scan.triangle_flags.get(t).is_some_and(|f| f.is_usable()) {
            continue;
        }
        let acc = f64::from(scan.triangle_accuracy.get(t).copied().unwrap_or(0.0));
        let acc = if acc.is_finite() {
            acc.clamp(0.0, 1.0)
        } else {
            0.0
        };
        let block = scan
            .vertex_pixel
            .get(tri[0] as usize)
            .and_then(|&p| grid.of_pixel(p as usize));
        if let Some(s) = block.and_then(|b| sums.get_mut(b)) {
            s.0 += acc;
            s.1 += 1;
        }
    }
    sums
}
