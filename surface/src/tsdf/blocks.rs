//! A field's blocks one at a time, as bytes: what an owner needs to keep a field
//! larger than its memory (the level-of-detail tree pages its fields' cold blocks
//! out). The field itself stays pure: the owner decides which blocks leave, stores
//! their bytes, and puts them back before any operation that reads them, which
//! [`Tsdf::keys_touched`] names in advance for fusion.

use std::collections::BTreeSet;

use super::{BLOCK_VOXELS, Block, BlockKey, Sample, Tsdf, Voxel, split};

/// Bytes of one encoded block: each voxel's distance, weight, colour sum and colour
/// weight as little-endian f32, voxel by voxel.
pub const BLOCK_BYTES: usize = BLOCK_VOXELS * VOXEL_BYTES;

const VOXEL_BYTES: usize = 24;

/// Why bytes are not a block.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BlockBytesError {
    #[error("a field block is {BLOCK_BYTES} bytes, got {0}")]
    Length(usize),
    #[error("field block voxel {slot}: {what}")]
    Voxel { slot: usize, what: &'static str },
}

impl Tsdf {
    /// Whether block `key` is held (it holds an observed voxel).
    pub fn has_block(&self, key: BlockKey) -> bool {
        self.blocks.contains_key(&key)
    }

    /// Block `key`'s bytes ([`BLOCK_BYTES`] of them), `None` when it is not held.
    pub fn encode_block(&self, key: BlockKey) -> Option<Vec<u8>> {
        let block = self.blocks.get(&key)?;
        let mut out = Vec::with_capacity(BLOCK_BYTES);
        for v in block.voxels.iter() {
            for x in [
                v.sdf_m,
                v.weight,
                v.colour_sum[0],
                v.colour_sum[1],
                v.colour_sum[2],
                v.colour_weight,
            ] {
                out.extend_from_slice(&x.to_le_bytes());
            }
        }
        Some(out)
    }

    /// Drops block `key` from memory (its owner keeps its bytes); whether it was held.
    pub fn drop_block(&mut self, key: BlockKey) -> bool {
        self.blocks.remove(&key).is_some()
    }

    /// Puts back block `key` from [`Self::encode_block`]'s bytes, replacing any block
    /// held there. Bytes that are not a block (wrong length, a non-finite value, a
    /// negative weight) are refused and the field is left as it was. A block with no
    /// observed voxel is not held.
    pub fn insert_block(&mut self, key: BlockKey, bytes: &[u8]) -> Result<(), BlockBytesError> {
        if bytes.len() != BLOCK_BYTES {
            return Err(BlockBytesError::Length(bytes.len()));
        }
        let mut block = Block::new();
        let mut observed = false;
        for (slot, (voxel, b)) in block
            .voxels
            .iter_mut()
            .zip(bytes.chunks_exact(VOXEL_BYTES))
            .enumerate()
        {
            let f = |k: usize| {
                let mut word = [0u8; 4];
                word.copy_from_slice(&b[4 * k..4 * k + 4]);
                f32::from_le_bytes(word)
            };
            let v = Voxel {
                sdf_m: f(0),
                weight: f(1),
                colour_sum: [f(2), f(3), f(4)],
                colour_weight: f(5),
            };
            let values = [
                v.sdf_m,
                v.weight,
                v.colour_sum[0],
                v.colour_sum[1],
                v.colour_sum[2],
                v.colour_weight,
            ];
            if values.iter().any(|x| !x.is_finite()) {
                return Err(BlockBytesError::Voxel {
                    slot,
                    what: "a value is not finite",
                });
            }
            if v.weight < 0.0 || v.colour_weight < 0.0 {
                return Err(BlockBytesError::Voxel {
                    slot,
                    what: "a weight is negative",
                });
            }
            observed |= v.weight > 0.0;
            *voxel = v;
        }
        if observed {
            self.blocks.insert(key, block);
        } else {
            self.blocks.remove(&key);
        }
        Ok(())
    }

    /// Adds to `keys` every block that fusing or removing `samples` would read or
    /// write: what must be held before [`Self::integrate`] or [`Self::remove`] runs
    /// on a field whose blocks are partly elsewhere.
    pub fn keys_touched(&self, samples: &[Sample], keys: &mut BTreeSet<BlockKey>) {
        let band = self.band();
        for sample in samples {
            // A ray's steps stay in one block for several voxels: set each once.
            let mut last = None;
            band.walk(sample, |index, _, _| {
                let key = split(index).0;
                if last != Some(key) {
                    last = Some(key);
                    keys.insert(key);
                }
            });
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;
    use crate::tsdf::TsdfConfig;

    fn wall() -> (Tsdf, Vec<Sample>) {
        let samples: Vec<Sample> = (-30..30)
            .flat_map(|y| (-10..10).map(move |z| (y, z)))
            .map(|(y, z)| Sample {
                point_m: [
                    2.0 + 0.003 * f64::from(y),
                    f64::from(y) * 0.02,
                    f64::from(z) * 0.02,
                ],
                centre_m: [0.0, 0.0, 0.0],
                weight: 0.9,
                colour: Some([200, 100, 50]),
            })
            .collect();
        let mut tsdf = Tsdf::new(TsdfConfig::default()).unwrap();
        tsdf.integrate(&samples);
        (tsdf, samples)
    }

    #[test]
    fn a_block_round_trips_through_its_bytes_bit_for_bit() {
        let (tsdf, _) = wall();
        let mut copy = Tsdf::new(TsdfConfig::default()).unwrap();
        for key in tsdf.block_keys() {
            let bytes = tsdf.encode_block(key).unwrap();
            assert_eq!(bytes.len(), BLOCK_BYTES);
            copy.insert_block(key, &bytes).unwrap();
        }
        assert_eq!(copy.block_count(), tsdf.block_count());
        for key in tsdf.block_keys() {
            assert_eq!(copy.encode_block(key), tsdf.encode_block(key));
        }
        assert!(tsdf.encode_block([99, 99, 99]).is_none());
    }

    #[test]
    fn bytes_that_are_not_a_block_are_refused_and_change_nothing() {
        let (mut tsdf, _) = wall();
        let key = tsdf.block_keys().next().unwrap();
        let good = tsdf.encode_block(key).unwrap();
        let e = tsdf.insert_block(key, &good[1..]).unwrap_err();
        assert!(e.to_string().contains("12288"), "{e}");
        let mut nan = good.clone();
        nan[24 * 7..24 * 7 + 4].copy_from_slice(&f32::NAN.to_le_bytes());
        let e = tsdf.insert_block(key, &nan).unwrap_err();
        assert!(e.to_string().contains("voxel 7"), "{e}");
        let mut negative = good.clone();
        negative[24 * 3 + 4..24 * 3 + 8].copy_from_slice(&(-1.0f32).to_le_bytes());
        assert!(tsdf.insert_block(key, &negative).is_err());
        assert_eq!(tsdf.encode_block(key).unwrap(), good);
        // An all-unobserved block is not held.
        tsdf.insert_block(key, &[0u8; BLOCK_BYTES]).unwrap();
        assert!(!tsdf.has_block(key));
    }

    #[test]
    fn keys_touched_name_every_block_fusion_changes() {
        let (tsdf, samples) = wall();
        let mut keys = BTreeSet::new();
        tsdf.keys_touched(&samples, &mut keys);
        let held: BTreeSet<BlockKey> = tsdf.block_keys().collect();
        assert_eq!(keys, held);
        // Fusion into a field missing one of them would differ: the names matter.
        let mut changed = BTreeSet::new();
        let mut again = Tsdf::new(TsdfConfig::default()).unwrap();
        again.integrate_marking(&samples, &mut changed);
        assert_eq!(changed, keys);
    }
}
