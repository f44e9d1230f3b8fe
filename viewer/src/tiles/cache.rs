//! The GPU tile cache: each decoded tile's mesh uploaded once (vertices as f32 offsets
//! from the tile's f64 origin with their colour, and u32 indices), keyed by tile id
//! and revision (a rebuilt tile has a new revision and replaces the old copy); its GPU
//! bytes kept within a budget by evicting the least recently used tiles first, never
//! one used in the current frame.

use std::collections::BTreeMap;

use bytemuck::{Pod, Zeroable};
use texel_lod::{LodNode, TileId};
use wgpu::util::DeviceExt;

use crate::gpu::{GpuContext, GpuError};

/// One vertex as the tile pass reads it: position relative to the tile's origin and
/// the colour (display values, alpha unused).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct TileVertex {
    pub position: [f32; 3],
    pub colour: [u8; 4],
}

/// The vertex layout of [`TileVertex`] (`TileIn` in `tile.wgsl`).
pub const TILE_VERTEX_ATTRIBUTES: [wgpu::VertexAttribute; 2] =
    wgpu::vertex_attr_array![0 => Float32x3, 1 => Unorm8x4];

/// GPU bytes a tile's mesh takes: 16 bytes a vertex, 12 a triangle.
pub fn tile_gpu_bytes(node: &LodNode) -> u64 {
    node.mesh.vertex_count() as u64 * std::mem::size_of::<TileVertex>() as u64
        + node.mesh.triangle_count() as u64 * 12
}

/// A resident tile.
#[derive(Debug)]
pub struct GpuTile {
    pub id: TileId,
    pub revision: u64,
    /// World position the vertices are relative to.
    pub origin_m: [f64; 3],
    pub bytes: u64,
    pub triangles: u32,
    /// `None` for a tile without surface (resident, so selection can refine through
    /// it, but nothing to draw).
    pub(crate) buffers: Option<(wgpu::Buffer, wgpu::Buffer)>,
    last_used_frame: u64,
}

impl GpuTile {
    pub fn last_used_frame(&self) -> u64 {
        self.last_used_frame
    }
}

/// What an insertion did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Inserted {
    /// Uploaded (replacing an older revision, if one was resident), after evicting
    /// these tiles to stay within the budget.
    Uploaded { evicted: Vec<TileId> },
    /// The same or a newer revision is already resident: nothing changed.
    Stale { resident_revision: u64 },
    /// Not uploaded: it does not fit the budget even after evicting every tile not
    /// used in this frame. Nothing was evicted.
    OverBudget { needed_bytes: u64 },
}

/// Resident tiles within a GPU byte budget.
pub struct TileCache {
    device: wgpu::Device,
    budget_bytes: u64,
    tiles: BTreeMap<TileId, GpuTile>,
    resident_bytes: u64,
}

impl TileCache {
    pub fn new(gpu: &GpuContext, budget_bytes: u64) -> Self {
        Self {
            device: gpu.device.clone(),
            budget_bytes,
            tiles: BTreeMap::new(),
            resident_bytes: 0,
        }
    }

    pub fn budget_bytes(&self) -> u64 {
        self.budget_bytes
    }

    /// GPU bytes of every resident tile (never above the budget).
    pub fn resident_bytes(&self) -> u64 {
        self.resident_bytes
    }

    pub fn len(&self) -> usize {
        self.tiles.len()
    }

    pub fn is_empty(&self) -> bool {
        self.tiles.is_empty()
    }

    pub fn contains(&self, id: TileId) -> bool {
        self.tiles.contains_key(&id)
    }

    pub fn get(&self, id: TileId) -> Option<&GpuTile> {
        self.tiles.get(&id)
    }

    /// The resident revision of a tile.
    pub fn revision(&self, id: TileId) -> Option<u64> {
        self.tiles.get(&id).map(|t| t.revision)
    }

    pub fn ids(&self) -> impl Iterator<Item = TileId> + '_ {
        self.tiles.keys().copied()
    }

    /// Marks a resident tile used in `frame` (drawn, or passed through by selection):
    /// it is not evicted while `frame` is the current one. False if not resident.
    pub fn mark_used(&mut self, id: TileId, frame: u64) -> bool {
        match self.tiles.get_mut(&id) {
            Some(t) => {
                t.last_used_frame = t.last_used_frame.max(frame);
                true
            }
            None => false,
        }
    }

    /// Drops a tile; returns the bytes it held.
    pub fn remove(&mut self, id: TileId) -> Option<u64> {
        let t = self.tiles.remove(&id)?;
        self.resident_bytes = self.resident_bytes.saturating_sub(t.bytes);
        Some(t.bytes)
    }

    /// Uploads `node` as `revision` in `frame` (it counts as used in that frame),
    /// evicting least recently used tiles (finest first among equals) as the budget
    /// requires; tiles used in `frame` are never evicted.
    pub fn insert(
        &mut self,
        node: &LodNode,
        revision: u64,
        frame: u64,
    ) -> Result<Inserted, GpuError> {
        if let Some(t) = self.tiles.get(&node.id)
            && t.revision >= revision
        {
            return Ok(Inserted::Stale {
                resident_revision: t.revision,
            });
        }
        let needed_bytes = if node.mesh.is_empty() {
            0
        } else {
            tile_gpu_bytes(node)
        };
        let replaced_bytes = self.tiles.get(&node.id).map_or(0, |t| t.bytes);
        let after = self.resident_bytes.saturating_sub(replaced_bytes);
        let mut evict = Vec::new();
        if after.saturating_add(needed_bytes) > self.budget_bytes {
            let mut candidates: Vec<(u64, u8, TileId, u64)> = self
                .tiles
                .values()
                .filter(|t| t.id != node.id && t.last_used_frame < frame)
                .map(|t| (t.last_used_frame, t.id.lod, t.id, t.bytes))
                .collect();
            candidates.sort();
            let mut freed = 0u64;
            for (_, _, id, bytes) in candidates {
                if after.saturating_sub(freed).saturating_add(needed_bytes) <= self.budget_bytes {
                    break;
                }
                freed = freed.saturating_add(bytes);
                evict.push(id);
            }
            if after.saturating_sub(freed).saturating_add(needed_bytes) > self.budget_bytes {
                return Ok(Inserted::OverBudget { needed_bytes });
            }
        }
        let tile = self.upload(node, revision, frame)?;
        for id in &evict {
            self.remove(*id);
        }
        self.remove(node.id);
        self.resident_bytes = self.resident_bytes.saturating_add(tile.bytes);
        self.tiles.insert(node.id, tile);
        Ok(Inserted::Uploaded { evicted: evict })
    }

    fn upload(&self, node: &LodNode, revision: u64, frame: u64) -> Result<GpuTile, GpuError> {
        let mesh = &node.mesh;
        let limit = self.device.limits().max_buffer_size;
        let bytes = tile_gpu_bytes(node);
        if bytes > limit || mesh.triangle_count() > (u32::MAX / 3) as usize {
            return Err(GpuError::TooLarge {
                what: "a tile's mesh",
                bytes,
                limit,
            });
        }
        let n = mesh.vertex_count();
        let valid = mesh.triangles.iter().flatten().all(|&v| (v as usize) < n);
        let buffers = if mesh.is_empty() || !valid {
            // A mesh with an index out of range cannot come from the decoder (it
            // checks every index); drawn as nothing rather than read out of bounds.
            None
        } else {
            let vertices: Vec<TileVertex> = mesh
                .positions
                .iter()
                .enumerate()
                .map(|(i, p)| {
                    let c = mesh.colours.get(i).copied().unwrap_or([0; 3]);
                    TileVertex {
                        position: *p,
                        colour: [c[0], c[1], c[2], 255],
                    }
                })
                .collect();
            let indices: Vec<u32> = mesh.triangles.iter().flatten().copied().collect();
            let label = format!("tile {}", node.id.path());
            let vb = self
                .device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(&label),
                    contents: bytemuck::cast_slice(&vertices),
                    usage: wgpu::BufferUsages::VERTEX,
                });
            let ib = self
                .device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(&label),
                    contents: bytemuck::cast_slice(&indices),
                    usage: wgpu::BufferUsages::INDEX,
                });
            Some((vb, ib))
        };
        let triangles = if buffers.is_some() {
            mesh.triangle_count() as u32
        } else {
            0
        };
        Ok(GpuTile {
            id: node.id,
            revision,
            origin_m: mesh.origin_m,
            bytes: if buffers.is_some() { bytes } else { 0 },
            triangles,
            buffers,
            last_used_frame: frame,
        })
    }
}
