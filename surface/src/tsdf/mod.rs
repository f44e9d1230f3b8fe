//! The truncated signed distance field: sparse 8³ blocks of voxels keyed by their
//! integer index in the world, so a model 5,000 km from the origin has the same
//! resolution as one at the origin (voxel centres are computed in f64).

use std::collections::HashMap;

use thiserror::Error;

mod blocks;
pub use blocks::{BLOCK_BYTES, BlockBytesError};

/// A voxel's integer index: its centre is at `origin + (index + 0.5) * voxel_m` in
/// the world.
pub type VoxelIndex = [i64; 3];

/// A block of 8³ voxels: its lowest voxel is `key * 8`.
pub type BlockKey = [i64; 3];

/// The block of the field at twice the voxel size that holds block `key`'s voxels.
pub fn parent_block(key: BlockKey) -> BlockKey {
    key.map(|k| k.div_euclid(2))
}

const BLOCK_SIDE: i64 = 8;
const BLOCK_VOXELS: usize = 512;

/// One voxel's fused state.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Voxel {
    /// Signed distance to the surface along the viewing rays, metres: positive in
    /// front of the surface (free space), negative behind it.
    pub sdf_m: f32,
    /// Sum of the weights of the samples fused here; 0 means never observed.
    pub weight: f32,
    /// Weighted sum of colours (linear in the 8-bit values).
    pub colour_sum: [f32; 3],
    pub colour_weight: f32,
}

impl Voxel {
    /// The fused colour, `None` where no textured sample reached the voxel.
    pub fn colour(&self) -> Option<[u8; 3]> {
        // Guard: a zero colour weight has no colour (not a division by zero).
        if self.colour_weight <= 0.0 {
            return None;
        }
        let c = |k: usize| {
            (self.colour_sum[k] / self.colour_weight)
                .round()
                .clamp(0.0, 255.0) as u8
        };
        Some([c(0), c(1), c(2)])
    }
}

#[derive(Debug, Clone)]
struct Block {
    voxels: Box<[Voxel; BLOCK_VOXELS]>,
}

impl Block {
    fn new() -> Self {
        Self {
            voxels: Box::new([Voxel::default(); BLOCK_VOXELS]),
        }
    }
}

/// How fine the field is and how far behind and before a surface it reaches.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TsdfConfig {
    /// Edge of a voxel, metres.
    pub voxel_m: f64,
    /// Half-width of the band around a surface that a sample updates, in voxels. Three
    /// voxels cover the range noise of a scan seen at the voxel size, and the
    /// neighbouring voxels that surface extraction interpolates between.
    pub truncation_voxels: f64,
}

impl Default for TsdfConfig {
    fn default() -> Self {
        Self {
            voxel_m: 0.05,
            truncation_voxels: 3.0,
        }
    }
}

#[derive(Debug, Error, PartialEq)]
pub enum TsdfError {
    #[error("TSDF {field} must be {expected}, got {value}")]
    BadConfig {
        field: &'static str,
        expected: &'static str,
        value: f64,
    },
}

/// One return to fuse: the surface point, the centre of projection it was seen from,
/// how reliable it is and its colour.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    pub point_m: [f64; 3],
    pub centre_m: [f64; 3],
    /// In (0, 1]: the normal accuracy of the surface there (Killpack & Budge 2016 §3.1),
    /// the cosine between the viewing ray and the surface normal. It weighs the
    /// sample and turns distances along the ray into distances across the surface.
    pub weight: f32,
    pub colour: Option<[u8; 3]>,
}

/// A sparse truncated signed distance field (Curless & Levoy 1996).
#[derive(Debug, Clone)]
pub struct Tsdf {
    config: TsdfConfig,
    /// Voxel `[0, 0, 0]` starts here (world metres).
    origin_m: [f64; 3],
    blocks: HashMap<[i64; 3], Block>,
}

impl Tsdf {
    pub fn new(config: TsdfConfig) -> Result<Self, TsdfError> {
        let bad = |field, expected, value| TsdfError::BadConfig {
            field,
            expected,
            value,
        };
        if !(config.voxel_m.is_finite() && config.voxel_m >= 1e-4 && config.voxel_m <= 1e4) {
            return Err(bad("voxel_m", "in [1e-4, 1e4]", config.voxel_m));
        }
        if !(config.truncation_voxels.is_finite()
            && (1.0..=64.0).contains(&config.truncation_voxels))
        {
            return Err(bad(
                "truncation_voxels",
                "in [1, 64]",
                config.truncation_voxels,
            ));
        }
        Ok(Self {
            config,
            origin_m: [0.0; 3],
            blocks: HashMap::new(),
        })
    }

    pub fn config(&self) -> TsdfConfig {
        self.config
    }

    pub fn voxel_m(&self) -> f64 {
        self.config.voxel_m
    }

    pub fn truncation_m(&self) -> f64 {
        self.config.voxel_m * self.config.truncation_voxels
    }

    pub fn block_count(&self) -> usize {
        self.blocks.len()
    }

    /// Bytes held by the blocks.
    pub fn heap_bytes(&self) -> usize {
        self.blocks.len() * (BLOCK_VOXELS * std::mem::size_of::<Voxel>() + 48)
    }

    /// The voxel containing a world point. Points beyond ±2^62 voxels saturate.
    pub fn index_of(&self, point_m: [f64; 3]) -> VoxelIndex {
        [0, 1, 2].map(|a| ((point_m[a] - self.origin_m[a]) / self.config.voxel_m).floor() as i64)
    }

    /// A voxel's centre in the world.
    pub fn centre_of(&self, index: VoxelIndex) -> [f64; 3] {
        [0, 1, 2].map(|a| self.origin_m[a] + (index[a] as f64 + 0.5) * self.config.voxel_m)
    }

    /// Where voxel `[0, 0, 0]` starts.
    pub fn origin_m(&self) -> [f64; 3] {
        self.origin_m
    }

    /// The same field with voxel `by` renamed `[0, 0, 0]`: a change of names, not of
    /// samples. `by` must be a whole number of blocks (multiples of 8) on each axis.
    pub fn reanchored(self, by: [i64; 3]) -> Result<Tsdf, TsdfError> {
        if let Some(&bad) = by.iter().find(|b| b.rem_euclid(BLOCK_SIDE) != 0) {
            return Err(TsdfError::BadConfig {
                field: "anchor",
                expected: "a multiple of 8 voxels",
                value: bad as f64,
            });
        }
        let shift = by.map(|b| b / BLOCK_SIDE);
        let origin_m = self.centre_of(by).map(|c| c - 0.5 * self.config.voxel_m);
        let blocks = self
            .blocks
            .into_iter()
            .map(|(key, block)| ([0, 1, 2].map(|a| key[a] - shift[a]), block))
            .collect();
        Ok(Tsdf {
            config: self.config,
            origin_m,
            blocks,
        })
    }

    /// The voxel at `index` if it was ever observed.
    pub fn voxel(&self, index: VoxelIndex) -> Option<&Voxel> {
        let (key, slot) = split(index);
        let voxel = &self.blocks.get(&key)?.voxels[slot];
        (voxel.weight > 0.0).then_some(voxel)
    }

    /// Fuses `samples`: each updates the voxels along its viewing ray within the
    /// truncation band around its point with the signed distance to the surface, a
    /// running mean weighted by the square of the sample's normal accuracy (a grazing
    /// view's distance is least certain, and the square lets head-on views outvote
    /// it where both reach). Samples with a non-finite coordinate, a non-positive
    /// weight or no length between centre and point are skipped. Returns the number
    /// of voxel updates.
    ///
    /// The distance along the ray is scaled by the sample's normal accuracy (the
    /// cosine between ray and surface normal) to approximate the distance
    /// perpendicular to the surface: a wall seen at a grazing angle would otherwise
    /// store distances stretched by 1/cos, and neighbouring voxels would differ by
    /// several voxels across the surface. The ray segment in front of the point is
    /// stretched by the same factor (at most fourfold) so the band keeps its width
    /// across the surface there.
    pub fn integrate(&mut self, samples: &[Sample]) -> usize {
        self.apply(samples, Direction::Add, None)
    }

    /// [`Self::integrate`], adding the keys of the blocks it changed to `changed`.
    pub fn integrate_marking(
        &mut self,
        samples: &[Sample],
        changed: &mut std::collections::BTreeSet<BlockKey>,
    ) -> usize {
        self.apply(samples, Direction::Add, Some(changed))
    }

    /// [`Self::remove`], adding the keys of the blocks it changed to `changed`.
    pub fn remove_marking(
        &mut self,
        samples: &[Sample],
        changed: &mut std::collections::BTreeSet<BlockKey>,
    ) -> usize {
        self.apply(samples, Direction::Remove, Some(changed))
    }

    /// Takes `samples` back out (de-integration): the exact inverse of
    /// [`Self::integrate`] with the same samples, up to rounding. A voxel whose weight
    /// falls to nothing becomes unobserved again, and blocks left with no observed
    /// voxel are freed. This is how a scan whose pose was revised moves: out at its
    /// old pose, in at its new one. Returns the number of voxel updates.
    pub fn remove(&mut self, samples: &[Sample]) -> usize {
        self.apply(samples, Direction::Remove, None)
    }

    fn apply(
        &mut self,
        samples: &[Sample],
        direction: Direction,
        mut changed: Option<&mut std::collections::BTreeSet<BlockKey>>,
    ) -> usize {
        let band = self.band();
        let mut touched: Vec<[i64; 3]> = Vec::new();
        let mut updates = 0usize;
        for sample in samples {
            band.walk(sample, |index, sdf, weight| {
                let (key, slot) = split(index);
                if let Some(changed) = changed.as_deref_mut()
                    && (direction == Direction::Add || self.blocks.contains_key(&key))
                {
                    changed.insert(key);
                }
                match direction {
                    Direction::Add => {
                        let block = self.blocks.entry(key).or_insert_with(Block::new);
                        fuse_into(&mut block.voxels[slot], sdf, weight, sample.colour);
                    }
                    Direction::Remove => {
                        let Some(block) = self.blocks.get_mut(&key) else {
                            return;
                        };
                        unfuse(&mut block.voxels[slot], sdf, weight, sample.colour);
                        if touched.last() != Some(&key) {
                            touched.push(key);
                        }
                    }
                }
                updates += 1;
            });
        }
        touched.sort_unstable();
        touched.dedup();
        for key in touched {
            let empty = self
                .blocks
                .get(&key)
                .is_some_and(|b| b.voxels.iter().all(|v| v.weight <= 0.0));
            if empty {
                self.blocks.remove(&key);
            }
        }
        updates
    }

    /// Where samples reach in this field: its voxel grid and truncation band.
    fn band(&self) -> Band {
        Band {
            voxel_m: self.config.voxel_m,
            truncation_m: self.truncation_m(),
            origin_m: self.origin_m,
        }
    }

    /// The field at twice the voxel size, from the same origin: each coarse voxel is
    /// the weighted mean of its eight children (their centres average to its centre,
    /// so a planar field stays exact). The truncation band keeps its width in metres where it can
    /// (at least one coarse voxel).
    pub fn downsampled(&self) -> Tsdf {
        let mut coarse = self.coarser_empty();
        let parents: std::collections::BTreeSet<BlockKey> =
            self.blocks.keys().map(|k| parent_block(*k)).collect();
        for key in parents {
            coarse.resample_block(self, key);
        }
        coarse
    }

    /// An empty field at twice this one's voxel size, from the same origin, with the
    /// truncation band's width in metres kept where it can be (at least one voxel).
    pub fn coarser_empty(&self) -> Tsdf {
        let voxel_m = self.config.voxel_m * 2.0;
        Tsdf {
            config: TsdfConfig {
                voxel_m,
                truncation_voxels: (self.truncation_m() / voxel_m).max(1.0),
            },
            origin_m: self.origin_m,
            blocks: HashMap::new(),
        }
    }

    /// Recomputes block `key` of this field from `fine`, the field at half its voxel
    /// size (the one it was made coarser from): each voxel the weighted mean of its
    /// eight children, summed in a fixed order so one field always gives the same
    /// bits. A block left with no observed voxel is freed. This is how a coarse field
    /// follows its fine one incrementally: only the blocks above changed ones.
    pub fn resample_block(&mut self, fine: &Tsdf, key: BlockKey) {
        let mut block = Block::new();
        let mut observed = false;
        for child in 0..8usize {
            let child_key = [0, 1, 2].map(|a| key[a] * 2 + ((child >> a) & 1) as i64);
            let Some(fine_block) = fine.blocks.get(&child_key) else {
                continue;
            };
            for (slot, v) in fine_block.voxels.iter().enumerate() {
                if v.weight <= 0.0 {
                    continue;
                }
                let parent = join(child_key, slot).map(|i| i.div_euclid(2));
                let (_, pslot) = split(parent);
                let voxel = &mut block.voxels[pslot];
                let w = voxel.weight + v.weight;
                // w > 0: v.weight > 0.
                voxel.sdf_m = (voxel.sdf_m * voxel.weight + v.sdf_m * v.weight) / w;
                voxel.weight = w;
                for (sum, c) in voxel.colour_sum.iter_mut().zip(v.colour_sum) {
                    *sum += c;
                }
                voxel.colour_weight += v.colour_weight;
                observed = true;
            }
        }
        if observed {
            self.blocks.insert(key, block);
        } else {
            self.blocks.remove(&key);
        }
    }

    /// Keys of the blocks that hold observed voxels.
    pub fn block_keys(&self) -> impl Iterator<Item = BlockKey> + '_ {
        self.blocks.keys().copied()
    }

    /// Inclusive bounds of the observed voxels, `None` when nothing was fused.
    pub fn bounds(&self) -> Option<(VoxelIndex, VoxelIndex)> {
        let mut keys = self.blocks.keys();
        let first = *keys.next()?;
        let (lo, hi) = keys.fold((first, first), |(mut lo, mut hi), k| {
            for a in 0..3 {
                lo[a] = lo[a].min(k[a]);
                hi[a] = hi[a].max(k[a]);
            }
            (lo, hi)
        });
        Some((
            lo.map(|b| b * BLOCK_SIDE),
            hi.map(|b| b * BLOCK_SIDE + BLOCK_SIDE - 1),
        ))
    }

    /// The lowest voxel of every block that holds an observed voxel.
    pub fn block_corners(&self) -> impl Iterator<Item = VoxelIndex> + '_ {
        self.blocks.keys().map(|key| key.map(|k| k * BLOCK_SIDE))
    }

    /// Every observed voxel whose x and y index lie in `[lo, hi)`, in no set order.
    pub fn voxels_in_columns(
        &self,
        lo: [i64; 2],
        hi: [i64; 2],
    ) -> impl Iterator<Item = (VoxelIndex, &Voxel)> + '_ {
        let block_lo = lo.map(|i| i.div_euclid(BLOCK_SIDE));
        let block_hi = hi.map(|i| (i - 1).div_euclid(BLOCK_SIDE));
        self.blocks
            .iter()
            .filter(move |(key, _)| (0..2).all(|a| key[a] >= block_lo[a] && key[a] <= block_hi[a]))
            .flat_map(move |(key, block)| {
                block
                    .voxels
                    .iter()
                    .enumerate()
                    .map(move |(slot, v)| (join(*key, slot), v))
                    .filter(move |(index, v)| {
                        v.weight > 0.0 && (0..2).all(|a| index[a] >= lo[a] && index[a] < hi[a])
                    })
            })
    }
}

/// A field's voxel grid and truncation band: the voxels a sample updates, apart from
/// the field's blocks (so the walk can run while they change).
#[derive(Debug, Clone, Copy)]
struct Band {
    voxel_m: f64,
    truncation_m: f64,
    origin_m: [f64; 3],
}

impl Band {
    /// Calls `visit(index, sdf_m, weight)` for each voxel `sample` updates: along its
    /// viewing ray within the truncation band round its point (see
    /// [`Tsdf::integrate`]), each voxel once per run of steps through it. Degenerate
    /// samples visit nothing.
    fn walk(&self, sample: &Sample, mut visit: impl FnMut(VoxelIndex, f32, f32)) {
        let Some(dir) = unit_ray(sample) else {
            return;
        };
        let weight = sample.weight.min(1.0);
        if weight.is_nan() || weight <= 0.0 {
            return;
        }
        let (voxel_m, truncation_m) = (self.voxel_m, self.truncation_m);
        let cos = f64::from(weight).max(0.25);
        // In front of the point the ray crossed free space: stretch the band
        // there. Behind it nothing is known, and a ray grazing a curved surface
        // leaves it again: keep the plain band.
        let front_m = truncation_m / cos;
        // Half-voxel steps along the ray reach every voxel the band crosses;
        // consecutive repeats of one voxel are fused once.
        let steps = ((front_m + truncation_m) / (0.5 * voxel_m)).ceil() as i64;
        let mut last: Option<VoxelIndex> = None;
        for step in 0..=steps {
            let s = -front_m + step as f64 * 0.5 * voxel_m;
            let x = [0, 1, 2].map(|k| sample.point_m[k] + s * dir[k]);
            let index = [0, 1, 2].map(|a| ((x[a] - self.origin_m[a]) / voxel_m).floor() as i64);
            if last == Some(index) {
                continue;
            }
            last = Some(index);
            let centre = [0, 1, 2].map(|a| self.origin_m[a] + (index[a] as f64 + 0.5) * voxel_m);
            // Distance of the voxel centre in front of the point, along the ray,
            // then across the surface.
            let along = (0..3)
                .map(|k| (sample.point_m[k] - centre[k]) * dir[k])
                .sum::<f64>();
            let sdf = along * cos;
            if sdf.abs() > truncation_m {
                continue;
            }
            visit(index, sdf as f32, weight * weight);
        }
    }
}

/// The unit direction from the centre to the point, `None` for a degenerate sample
/// (non-finite coordinates or centre and point closer than a micrometre).
fn unit_ray(sample: &Sample) -> Option<[f64; 3]> {
    let d = [0, 1, 2].map(|k| sample.point_m[k] - sample.centre_m[k]);
    let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    if !len.is_finite() || len < 1e-6 {
        return None;
    }
    Some(d.map(|x| x / len))
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Direction {
    Add,
    Remove,
}

/// The weighted running mean of Curless & Levoy (1996), eq. 1-2. Weights are not
/// capped, so a sample can be taken out again exactly ([`unfuse`]).
fn fuse_into(voxel: &mut Voxel, sdf_m: f32, weight: f32, colour: Option<[u8; 3]>) {
    let w = voxel.weight + weight;
    // w > 0: weight > 0.
    voxel.sdf_m = (voxel.sdf_m * voxel.weight + sdf_m * weight) / w;
    voxel.weight = w;
    if let Some(c) = colour {
        // Weighted like the distance: the most reliable views colour the surface.
        for (sum, channel) in voxel.colour_sum.iter_mut().zip(c) {
            *sum += f32::from(channel) * weight;
        }
        voxel.colour_weight += weight;
    }
}

/// Weights below this share of a sample's own are rounding left-overs: the voxel has
/// no observation left.
const EMPTY_WEIGHT: f32 = 1e-4;

/// The inverse of [`fuse_into`]: the running mean without the sample.
fn unfuse(voxel: &mut Voxel, sdf_m: f32, weight: f32, colour: Option<[u8; 3]>) {
    let w = voxel.weight - weight;
    // Guard: a voxel left with (almost) no weight has no mean; it is unobserved.
    if w <= EMPTY_WEIGHT * weight {
        *voxel = Voxel::default();
        return;
    }
    voxel.sdf_m = (voxel.sdf_m * voxel.weight - sdf_m * weight) / w;
    voxel.weight = w;
    if let Some(c) = colour {
        for (sum, channel) in voxel.colour_sum.iter_mut().zip(c) {
            *sum -= f32::from(channel) * weight;
        }
        voxel.colour_weight -= weight;
        if voxel.colour_weight <= EMPTY_WEIGHT * weight {
            voxel.colour_sum = [0.0; 3];
            voxel.colour_weight = 0.0;
        }
    }
}

fn split(index: VoxelIndex) -> ([i64; 3], usize) {
    let key = index.map(|i| i.div_euclid(BLOCK_SIDE));
    let local = index.map(|i| i.rem_euclid(BLOCK_SIDE) as usize);
    (key, local[0] + 8 * local[1] + 64 * local[2])
}

fn join(key: [i64; 3], slot: usize) -> VoxelIndex {
    let local = [slot % 8, (slot / 8) % 8, slot / 64];
    [0, 1, 2].map(|a| key[a] * BLOCK_SIDE + local[a] as i64)
}

#[cfg(test)]
mod tests;
