//! The GPU tile cache: each decoded tile's mesh uploaded once (vertices as f32 offsets
//! from the tile's f64 origin with their colour and atlas coordinates, u32 indices,
//! and the tile's atlas as an RGBA texture where it has one), keyed by tile id
//! and revision (a rebuilt tile has a new revision and replaces the old copy); its GPU
//! bytes kept within a budget by evicting the least recently used tiles first, never
//! one used in the current frame.

use std::collections::BTreeMap;

use bytemuck::{Pod, Zeroable};
use texel_lod::{LodNode, TileId, TileTexture};
use wgpu::util::DeviceExt;

use crate::gpu::{GpuContext, GpuError};

/// One vertex as the tile pass reads it: position relative to the tile's origin, the
/// colour (display values, alpha unused; white where the atlas holds the colour, as
/// the shader multiplies the two) and the atlas coordinates.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct TileVertex {
    pub position: [f32; 3],
    pub colour: [u8; 4],
    pub uv: [f32; 2],
}

/// The vertex layout of [`TileVertex`] (`TileIn` in `tile.wgsl`).
pub const TILE_VERTEX_ATTRIBUTES: [wgpu::VertexAttribute; 3] =
    wgpu::vertex_attr_array![0 => Float32x3, 1 => Unorm8x4, 2 => Float32x2];

/// The atlas texture's format: plain (not sRGB) 8-bit, so a sample is the display
/// value the atlas holds, filtered between display values as the vertex colours are
/// interpolated; the shader treats both alike.
pub const ATLAS_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;

/// The atlas of a tile if it is one the GPU can hold: its size matches its texels and
/// coordinates, and no side exceeds `max_side` texels.
fn drawable_atlas(node: &LodNode, max_side: u32) -> Option<&TileTexture> {
    node.texture.as_ref().filter(|t| {
        t.width > 0
            && t.height > 0
            && t.width <= max_side
            && t.height <= max_side
            && t.rgb.len() == t.width as usize * t.height as usize * 3
            && t.uvs.len() == node.mesh.vertex_count()
    })
}

/// GPU bytes a tile takes: 24 bytes a vertex, 12 a triangle, and 4 a texel of its
/// atlas (RGBA: GPUs have no 3-byte texel).
pub fn tile_gpu_bytes(node: &LodNode) -> u64 {
    mesh_gpu_bytes(node) + drawable_atlas(node, u32::MAX).map_or(0, atlas_gpu_bytes)
}

fn mesh_gpu_bytes(node: &LodNode) -> u64 {
    node.mesh.vertex_count() as u64 * std::mem::size_of::<TileVertex>() as u64
        + node.mesh.triangle_count() as u64 * 12
}

fn atlas_gpu_bytes(texture: &TileTexture) -> u64 {
    u64::from(texture.width) * u64::from(texture.height) * 4
}

/// Surface points kept per resident tile: enough to tell which of a tile's scans
/// saw which part of it, 3 KiB a tile.
pub const SURFACE_SAMPLES: usize = 128;

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
    /// The tile's atlas; `None` for a tile coloured per vertex.
    pub(crate) atlas: Option<wgpu::TextureView>,
    /// Points spread over its surface by area, world metres (which scans saw the
    /// tile: `scan_choice.rs`).
    pub samples_m: Vec<[f64; 3]>,
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
    queue: wgpu::Queue,
    budget_bytes: u64,
    tiles: BTreeMap<TileId, GpuTile>,
    resident_bytes: u64,
}

impl TileCache {
    pub fn new(gpu: &GpuContext, budget_bytes: u64) -> Self {
        Self {
            device: gpu.device.clone(),
            queue: gpu.queue.clone(),
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
        let bytes = mesh_gpu_bytes(node);
        if bytes > limit || mesh.triangle_count() > (u32::MAX / 3) as usize {
            return Err(GpuError::TooLarge {
                what: "a tile's mesh",
                bytes,
                limit,
            });
        }
        let n = mesh.vertex_count();
        let valid = mesh.triangles.iter().flatten().all(|&v| (v as usize) < n);
        // An atlas too large for this GPU is left out: the vertex colours show.
        let texture = drawable_atlas(node, self.device.limits().max_texture_dimension_2d)
            .filter(|_| valid && !mesh.is_empty());
        let bytes = bytes + texture.map_or(0, atlas_gpu_bytes);
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
                    let (c, uv) = match texture {
                        Some(t) => ([255; 3], t.uvs.get(i).copied().unwrap_or([0.0; 2])),
                        None => (mesh.colours.get(i).copied().unwrap_or([0; 3]), [0.0; 2]),
                    };
                    TileVertex {
                        position: *p,
                        colour: [c[0], c[1], c[2], 255],
                        uv,
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
        let atlas = texture
            .filter(|_| buffers.is_some())
            .map(|t| self.upload_atlas(t, &node.id.path()));
        let buffers_drawn = buffers.is_some();
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
            atlas,
            samples_m: if buffers_drawn {
                mesh.area_samples(SURFACE_SAMPLES)
            } else {
                Vec::new()
            },
            last_used_frame: frame,
        })
    }

    /// A tile's atlas as an RGBA texture.
    fn upload_atlas(&self, texture: &TileTexture, path: &str) -> wgpu::TextureView {
        let rgba: Vec<u8> = texture
            .rgb
            .chunks_exact(3)
            .flat_map(|c| [c[0], c[1], c[2], 255])
            .collect();
        atlas_view(
            &self.device,
            &self.queue,
            &format!("tile atlas {path}"),
            (texture.width, texture.height),
            &rgba,
        )
    }
}

/// An `ATLAS_FORMAT` texture of `size` holding `rgba`, as the tile pass binds it.
fn atlas_view(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    label: &str,
    (width, height): (u32, u32),
    rgba: &[u8],
) -> wgpu::TextureView {
    device
        .create_texture_with_data(
            queue,
            &wgpu::TextureDescriptor {
                label: Some(label),
                size: wgpu::Extent3d {
                    width,
                    height,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: ATLAS_FORMAT,
                usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
                view_formats: &[],
            },
            wgpu::util::TextureDataOrder::LayerMajor,
            rgba,
        )
        .create_view(&wgpu::TextureViewDescriptor::default())
}

/// What binds a tile's atlas in the tile pass (group 1 beside the tile's uniform,
/// bindings 1 and 2): a bilinear sampler clamped to the edge (the charts' one-texel
/// gutters are all a bilinear tap reaches; no mipmaps), and a 1 × 1 white atlas for
/// tiles coloured per vertex.
pub(crate) struct AtlasBinding {
    sampler: wgpu::Sampler,
    blank: wgpu::TextureView,
}

/// The layout entries of the atlas and its sampler.
pub(crate) const ATLAS_LAYOUT_ENTRIES: [wgpu::BindGroupLayoutEntry; 2] = [
    wgpu::BindGroupLayoutEntry {
        binding: 1,
        visibility: wgpu::ShaderStages::FRAGMENT,
        ty: wgpu::BindingType::Texture {
            sample_type: wgpu::TextureSampleType::Float { filterable: true },
            view_dimension: wgpu::TextureViewDimension::D2,
            multisampled: false,
        },
        count: None,
    },
    wgpu::BindGroupLayoutEntry {
        binding: 2,
        visibility: wgpu::ShaderStages::FRAGMENT,
        ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
        count: None,
    },
];

impl AtlasBinding {
    pub(crate) fn new(device: &wgpu::Device, queue: &wgpu::Queue) -> Self {
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("tile atlas"),
            address_mode_u: wgpu::AddressMode::ClampToEdge,
            address_mode_v: wgpu::AddressMode::ClampToEdge,
            address_mode_w: wgpu::AddressMode::ClampToEdge,
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            ..Default::default()
        });
        let blank = atlas_view(device, queue, "blank tile atlas", (1, 1), &[255; 4]);
        Self { sampler, blank }
    }

    /// Group 1 of the tile pass: `uniform_bytes` of `uniforms` (at a dynamic offset)
    /// and `atlas`, or the blank atlas.
    pub(crate) fn bind_group(
        &self,
        device: &wgpu::Device,
        layout: &wgpu::BindGroupLayout,
        uniforms: &wgpu::Buffer,
        uniform_bytes: u64,
        atlas: Option<&wgpu::TextureView>,
    ) -> wgpu::BindGroup {
        device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tile"),
            layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: uniforms,
                        offset: 0,
                        size: wgpu::BufferSize::new(uniform_bytes),
                    }),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(atlas.unwrap_or(&self.blank)),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: wgpu::BindingResource::Sampler(&self.sampler),
                },
            ],
        })
    }
}
