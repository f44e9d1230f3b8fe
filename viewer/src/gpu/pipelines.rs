//! Long-lived GPU state: shader modules, bind group layouts, the sampler and every
//! pipeline. Built once per device; pipelines that write the caller's target are
//! built once per target format (the renderer keeps them by format). Each pipeline is
//! compiled on its first use ([`LazyPipeline`]): a frame needs only its mode's and
//! strategy's, and a software rasteriser (a browser without a GPU) spends long on
//! each compilation before it can draw anything.

use std::sync::OnceLock;

use super::scan_data::{VERTEX_ATTRIBUTES, Vertex};
use super::{DEPTH_FORMAT, LAYER_COLOUR_FORMAT, LAYER_DATA_FORMAT, NEAREST_FORMAT, shaders};

/// How a pipeline is built (kept until its first use).
enum Recipe {
    /// Scan meshes through `vs_scan` into `targets`.
    Scan {
        layout: wgpu::PipelineLayout,
        module: wgpu::ShaderModule,
        label: &'static str,
        fragment_entry: &'static str,
        targets: Vec<Option<wgpu::ColorTargetState>>,
        /// The depth buffer's format (`Pipelines::scan_depth`).
        depth_format: wgpu::TextureFormat,
        /// Writes the stencil reference where a fragment is kept.
        marks: bool,
    },
    /// `vs_fullscreen`'s one triangle into a `format` target.
    Fullscreen {
        layout: wgpu::PipelineLayout,
        module: wgpu::ShaderModule,
        label: &'static str,
        format: wgpu::TextureFormat,
    },
    /// `vs_fullscreen`'s one triangle over the depth buffer (always passing; written
    /// when `depth_write`, at depth 0): the k-buffer's merge (no colour output) and
    /// its layer clear.
    OverDepth {
        layout: wgpu::PipelineLayout,
        module: wgpu::ShaderModule,
        label: &'static str,
        fragment_entry: &'static str,
        depth_write: bool,
        targets: Vec<Option<wgpu::ColorTargetState>>,
        depth_format: wgpu::TextureFormat,
        /// Draws only where the stencil equals the reference.
        marked_only: bool,
    },
}

/// A render pipeline compiled the first time it is used (dereferenced), so a frame
/// compiles only the pipelines of its mode and strategy.
pub(crate) struct LazyPipeline {
    device: wgpu::Device,
    recipe: Recipe,
    built: OnceLock<wgpu::RenderPipeline>,
}

impl LazyPipeline {
    fn new(device: &wgpu::Device, recipe: Recipe) -> Self {
        Self {
            device: device.clone(),
            recipe,
            built: OnceLock::new(),
        }
    }
}

impl std::ops::Deref for LazyPipeline {
    type Target = wgpu::RenderPipeline;

    fn deref(&self) -> &wgpu::RenderPipeline {
        self.built.get_or_init(|| match &self.recipe {
            Recipe::Scan {
                layout,
                module,
                label,
                fragment_entry,
                targets,
                depth_format,
                marks,
            } => scan_render_pipeline(
                &self.device,
                layout,
                module,
                (label, fragment_entry),
                targets,
                *depth_format,
                *marks,
            ),
            Recipe::Fullscreen {
                layout,
                module,
                label,
                format,
            } => fullscreen_pipeline(&self.device, layout, module, label, "fs_composite", *format),
            Recipe::OverDepth {
                layout,
                module,
                label,
                fragment_entry,
                depth_write,
                targets,
                depth_format,
                marked_only,
            } => over_depth_pipeline(
                &self.device,
                layout,
                module,
                (label, fragment_entry),
                (*depth_format, *depth_write),
                targets,
                *marked_only,
            ),
        })
    }
}

/// Pipelines writing into the caller's target.
pub(crate) struct OutputPipelines {
    pub painter: LazyPipeline,
    /// `None` where the device has no storage buffers (`Pipelines::kbuffer`).
    pub composite_kbuffer: Option<LazyPipeline>,
    pub composite_naive: LazyPipeline,
}

/// The k-buffer's own state: it keeps each pixel's best fragments in a storage
/// buffer, which some devices (WebGL2) lack; there the naive layers composite.
pub(crate) struct KBufferPipelines {
    pub merge_layout: wgpu::BindGroupLayout,
    pub composite_layout: wgpu::BindGroupLayout,
    module: wgpu::ShaderModule,
    pipeline_layout: wgpu::PipelineLayout,
    pub merge: LazyPipeline,
    /// The merge only where a layer of the batch marked the stencil.
    pub merge_marked: LazyPipeline,
    /// One scan into one packed layer (`fs_layer_packed`).
    pub layer: LazyPipeline,
    /// Zeroes a layer and the depth buffer inside the scissor rectangle (the
    /// part of a layer a scan wrote, or is about to).
    pub clear_layer: LazyPipeline,
}

pub(crate) struct Pipelines {
    pub frame_layout: wgpu::BindGroupLayout,
    pub scan_layout: wgpu::BindGroupLayout,
    pub naive_layout: wgpu::BindGroupLayout,
    pub sampler: wgpu::Sampler,
    scan_module: wgpu::ShaderModule,
    naive_module: wgpu::ShaderModule,
    scan_pipeline_layout: wgpu::PipelineLayout,
    naive_pipeline_layout: wgpu::PipelineLayout,
    /// The renderer's depth buffer's format (`gpu::scan_depth_format`): with a
    /// stencil where the k-buffer can merge only marked pixels.
    pub scan_depth: wgpu::TextureFormat,
    pub prepass: LazyPipeline,
    pub layer: LazyPipeline,
    /// `None` on a device without storage buffers in fragment shaders.
    pub kbuffer: Option<KBufferPipelines>,
}

pub(crate) fn uniform_entry(
    binding: u32,
    visibility: wgpu::ShaderStages,
    dynamic: bool,
) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: dynamic,
            min_binding_size: None,
        },
        count: None,
    }
}

pub(crate) fn texture_entry(
    binding: u32,
    visibility: wgpu::ShaderStages,
    sample_type: wgpu::TextureSampleType,
    view_dimension: wgpu::TextureViewDimension,
) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility,
        ty: wgpu::BindingType::Texture {
            sample_type,
            view_dimension,
            multisampled: false,
        },
        count: None,
    }
}

pub(crate) fn storage_entry(
    binding: u32,
    visibility: wgpu::ShaderStages,
    read_only: bool,
) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

pub(crate) const UNFILTERED: wgpu::TextureSampleType =
    wgpu::TextureSampleType::Float { filterable: false };
const UINT: wgpu::TextureSampleType = wgpu::TextureSampleType::Uint;
pub(crate) const D2: wgpu::TextureViewDimension = wgpu::TextureViewDimension::D2;
const D2_ARRAY: wgpu::TextureViewDimension = wgpu::TextureViewDimension::D2Array;

fn primitive() -> wgpu::PrimitiveState {
    wgpu::PrimitiveState {
        topology: wgpu::PrimitiveTopology::TriangleList,
        // Fusion winds triangles with their normal towards the acquisition COP; with
        // the projection's y flip that is counter-clockwise on screen.
        front_face: wgpu::FrontFace::Ccw,
        cull_mode: Some(wgpu::Face::Back),
        ..Default::default()
    }
}

/// Reverse z: nearer is greater; on equal depth the first drawn (lower scan id) stays.
pub(crate) fn depth_state() -> Option<wgpu::DepthStencilState> {
    depth_state_for(DEPTH_FORMAT)
}

/// [`depth_state`] for a depth buffer of `format`.
fn depth_state_for(format: wgpu::TextureFormat) -> Option<wgpu::DepthStencilState> {
    Some(wgpu::DepthStencilState {
        format,
        depth_write_enabled: Some(true),
        depth_compare: Some(wgpu::CompareFunction::Greater),
        stencil: wgpu::StencilState::default(),
        bias: wgpu::DepthBiasState::default(),
    })
}

pub(crate) fn replace(format: wgpu::TextureFormat) -> Option<wgpu::ColorTargetState> {
    Some(wgpu::ColorTargetState {
        format,
        blend: None,
        write_mask: wgpu::ColorWrites::ALL,
    })
}

pub(crate) fn module(device: &wgpu::Device, name: &str, own: &str) -> wgpu::ShaderModule {
    device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(name),
        source: wgpu::ShaderSource::Wgsl(shaders::source(own).into()),
    })
}

impl Pipelines {
    pub fn new(device: &wgpu::Device) -> Self {
        let vf = wgpu::ShaderStages::VERTEX | wgpu::ShaderStages::FRAGMENT;
        let fs = wgpu::ShaderStages::FRAGMENT;
        let frame_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("frame"),
            entries: &[uniform_entry(0, vf, false)],
        });
        let scan_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("scan"),
            entries: &[
                uniform_entry(0, vf, false),
                texture_entry(
                    1,
                    fs,
                    wgpu::TextureSampleType::Float { filterable: true },
                    D2,
                ),
                wgpu::BindGroupLayoutEntry {
                    binding: 2,
                    visibility: fs,
                    ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
                    count: None,
                },
            ],
        });
        let naive_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("composite naive"),
            entries: &[
                uniform_entry(0, fs, false),
                texture_entry(1, fs, UNFILTERED, D2_ARRAY),
                texture_entry(2, fs, UINT, D2_ARRAY),
            ],
        });
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("EO bilinear"),
            address_mode_u: wgpu::AddressMode::ClampToEdge,
            address_mode_v: wgpu::AddressMode::ClampToEdge,
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            ..Default::default()
        });
        let layout = |label: &str, groups: &[Option<&wgpu::BindGroupLayout>]| {
            device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some(label),
                bind_group_layouts: groups,
                immediate_size: 0,
            })
        };
        let scan_pipeline_layout = layout("scan", &[Some(&frame_layout), Some(&scan_layout)]);
        let scan_depth = super::scan_depth_format(device);
        let marks = super::marks_supported(device);
        let naive_pipeline_layout = layout("composite naive", &[Some(&naive_layout)]);
        let scan_module = module(device, "scan.wgsl", shaders::SCAN);
        let naive_module = module(device, "composite_naive.wgsl", shaders::COMPOSITE_NAIVE);
        let scan_pipeline = |label, fragment_entry, targets| {
            LazyPipeline::new(
                device,
                Recipe::Scan {
                    layout: scan_pipeline_layout.clone(),
                    module: scan_module.clone(),
                    label,
                    fragment_entry,
                    targets,
                    depth_format: scan_depth,
                    marks: false,
                },
            )
        };
        let prepass = scan_pipeline("prepass", "fs_prepass", vec![replace(NEAREST_FORMAT)]);
        let layer = scan_pipeline(
            "layer",
            "fs_layer",
            vec![replace(LAYER_COLOUR_FORMAT), replace(LAYER_DATA_FORMAT)],
        );
        let kbuffer = (device.limits().max_storage_buffers_per_shader_stage > 0)
            .then(|| KBufferPipelines::new(device, &scan_pipeline_layout, &scan_module, marks));
        Self {
            frame_layout,
            scan_layout,
            naive_layout,
            sampler,
            scan_module,
            naive_module,
            scan_pipeline_layout,
            naive_pipeline_layout,
            scan_depth,
            prepass,
            layer,
            kbuffer,
        }
    }
}

impl KBufferPipelines {
    /// `marks`: the device can merge only marked pixels (`gpu::marks_supported`).
    fn new(
        device: &wgpu::Device,
        scan_pipeline_layout: &wgpu::PipelineLayout,
        scan_module: &wgpu::ShaderModule,
        marks: bool,
    ) -> Self {
        let depth_format = super::scan_depth_format(device);
        let fs = wgpu::ShaderStages::FRAGMENT;
        let mf = fs;
        let merge_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("merge"),
            entries: &[
                uniform_entry(0, mf, false),
                texture_entry(1, mf, UINT, D2),
                texture_entry(2, mf, UINT, D2_ARRAY),
                storage_entry(3, mf, false),
                uniform_entry(4, mf, true),
            ],
        });
        let composite_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("composite k-buffer"),
            entries: &[
                uniform_entry(0, fs, false),
                storage_entry(1, fs, true),
                texture_entry(2, fs, UINT, D2),
            ],
        });
        let layout = |label: &str, group: &wgpu::BindGroupLayout| {
            device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some(label),
                bind_group_layouts: &[Some(group)],
                immediate_size: 0,
            })
        };
        let merge_pipeline_layout = layout("merge", &merge_layout);
        let pipeline_layout = layout("composite k-buffer", &composite_layout);
        let merge_module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("merge.wgsl"),
            source: wgpu::ShaderSource::Wgsl(shaders::merge_source(marks).into()),
        });
        let module = module(device, "composite_kbuffer.wgsl", shaders::COMPOSITE_KBUFFER);
        let clear_layer = LazyPipeline::new(
            device,
            // Zeroes a packed layer and the depth buffer inside the pass's scissor
            // rectangle: the full-screen triangle lies at depth 0, reverse z's far
            // plane, what a cleared depth buffer holds.
            Recipe::OverDepth {
                layout: device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                    label: Some("clear layer"),
                    bind_group_layouts: &[],
                    immediate_size: 0,
                }),
                module: merge_module.clone(),
                label: "clear layer",
                fragment_entry: "fs_clear_layer",
                depth_write: true,
                targets: vec![replace(LAYER_DATA_FORMAT)],
                depth_format,
                marked_only: false,
            },
        );
        let merge_with = |marked_only| {
            LazyPipeline::new(
                device,
                // No colour output: the pass needs an attachment, so it takes the depth
                // buffer without writing it.
                Recipe::OverDepth {
                    layout: merge_pipeline_layout.clone(),
                    module: merge_module.clone(),
                    label: "merge (fragment)",
                    fragment_entry: "fs_merge",
                    depth_write: false,
                    targets: Vec::new(),
                    depth_format,
                    marked_only,
                },
            )
        };
        let merge = merge_with(false);
        // Where the device cannot mark pixels, the same as `merge` (and never used).
        let merge_marked = merge_with(marks);
        let layer = LazyPipeline::new(
            device,
            Recipe::Scan {
                layout: scan_pipeline_layout.clone(),
                module: scan_module.clone(),
                label: "packed layer",
                fragment_entry: "fs_layer_packed",
                targets: vec![replace(LAYER_DATA_FORMAT)],
                depth_format,
                marks,
            },
        );
        Self {
            merge_layout,
            composite_layout,
            module,
            pipeline_layout,
            merge,
            merge_marked,
            layer,
            clear_layer,
        }
    }
}

impl OutputPipelines {
    /// The pipelines writing into a target of `format` (each compiled on first use).
    pub fn new(device: &wgpu::Device, pipelines: &Pipelines, format: wgpu::TextureFormat) -> Self {
        Self {
            painter: LazyPipeline::new(
                device,
                Recipe::Scan {
                    layout: pipelines.scan_pipeline_layout.clone(),
                    module: pipelines.scan_module.clone(),
                    label: "painter",
                    fragment_entry: "fs_painter",
                    targets: vec![replace(format)],
                    depth_format: pipelines.scan_depth,
                    marks: false,
                },
            ),
            composite_kbuffer: pipelines.kbuffer.as_ref().map(|k| {
                LazyPipeline::new(
                    device,
                    Recipe::Fullscreen {
                        layout: k.pipeline_layout.clone(),
                        module: k.module.clone(),
                        label: "composite k-buffer",
                        format,
                    },
                )
            }),
            composite_naive: LazyPipeline::new(
                device,
                Recipe::Fullscreen {
                    layout: pipelines.naive_pipeline_layout.clone(),
                    module: pipelines.naive_module.clone(),
                    label: "composite naive",
                    format,
                },
            ),
        }
    }
}

/// `vs_fullscreen`'s triangle into `targets` over the depth buffer, which it always
/// passes and writes (at depth 0) only when `depth_write`.
fn over_depth_pipeline(
    device: &wgpu::Device,
    layout: &wgpu::PipelineLayout,
    module: &wgpu::ShaderModule,
    (label, fragment_entry): (&str, &str),
    (depth_format, depth_write): (wgpu::TextureFormat, bool),
    targets: &[Option<wgpu::ColorTargetState>],
    marked_only: bool,
) -> wgpu::RenderPipeline {
    let stencil = if marked_only {
        let face = wgpu::StencilFaceState {
            compare: wgpu::CompareFunction::Equal,
            fail_op: wgpu::StencilOperation::Keep,
            depth_fail_op: wgpu::StencilOperation::Keep,
            pass_op: wgpu::StencilOperation::Keep,
        };
        wgpu::StencilState {
            front: face,
            back: face,
            read_mask: 0xFF,
            write_mask: 0,
        }
    } else {
        wgpu::StencilState::default()
    };
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some(label),
        layout: Some(layout),
        vertex: wgpu::VertexState {
            module,
            entry_point: Some("vs_fullscreen"),
            compilation_options: Default::default(),
            buffers: &[],
        },
        primitive: wgpu::PrimitiveState::default(),
        depth_stencil: Some(wgpu::DepthStencilState {
            format: depth_format,
            depth_write_enabled: Some(depth_write),
            depth_compare: Some(wgpu::CompareFunction::Always),
            stencil,
            bias: wgpu::DepthBiasState::default(),
        }),
        multisample: wgpu::MultisampleState::default(),
        fragment: Some(wgpu::FragmentState {
            module,
            entry_point: Some(fragment_entry),
            compilation_options: Default::default(),
            targets,
        }),
        multiview_mask: None,
        cache: None,
    })
}

fn scan_render_pipeline(
    device: &wgpu::Device,
    layout: &wgpu::PipelineLayout,
    module: &wgpu::ShaderModule,
    (label, fragment_entry): (&str, &str),
    targets: &[Option<wgpu::ColorTargetState>],
    depth_format: wgpu::TextureFormat,
    marks: bool,
) -> wgpu::RenderPipeline {
    let mut depth_stencil = depth_state_for(depth_format);
    if let Some(d) = depth_stencil.as_mut().filter(|_| marks) {
        let face = wgpu::StencilFaceState {
            compare: wgpu::CompareFunction::Always,
            fail_op: wgpu::StencilOperation::Keep,
            depth_fail_op: wgpu::StencilOperation::Keep,
            pass_op: wgpu::StencilOperation::Replace,
        };
        d.stencil = wgpu::StencilState {
            front: face,
            back: face,
            read_mask: 0xFF,
            write_mask: 0xFF,
        };
    }
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some(label),
        layout: Some(layout),
        vertex: wgpu::VertexState {
            module,
            entry_point: Some("vs_scan"),
            compilation_options: Default::default(),
            buffers: &[Some(wgpu::VertexBufferLayout {
                array_stride: std::mem::size_of::<Vertex>() as u64,
                step_mode: wgpu::VertexStepMode::Vertex,
                attributes: &VERTEX_ATTRIBUTES,
            })],
        },
        primitive: primitive(),
        depth_stencil,
        multisample: wgpu::MultisampleState::default(),
        fragment: Some(wgpu::FragmentState {
            module,
            entry_point: Some(fragment_entry),
            compilation_options: Default::default(),
            targets,
        }),
        multiview_mask: None,
        cache: None,
    })
}

/// A pipeline drawing `vs_fullscreen`'s one triangle with `fragment_entry` into a
/// `format` target, replacing what is there (the composites, tone mapping).
pub(crate) fn fullscreen_pipeline(
    device: &wgpu::Device,
    layout: &wgpu::PipelineLayout,
    module: &wgpu::ShaderModule,
    label: &str,
    fragment_entry: &str,
    format: wgpu::TextureFormat,
) -> wgpu::RenderPipeline {
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some(label),
        layout: Some(layout),
        vertex: wgpu::VertexState {
            module,
            entry_point: Some("vs_fullscreen"),
            compilation_options: Default::default(),
            buffers: &[],
        },
        primitive: wgpu::PrimitiveState::default(),
        depth_stencil: None,
        multisample: wgpu::MultisampleState::default(),
        fragment: Some(wgpu::FragmentState {
            module,
            entry_point: Some(fragment_entry),
            compilation_options: Default::default(),
            targets: &[replace(format)],
        }),
        multiview_mask: None,
        cache: None,
    })
}

/// A pipeline drawing a two-sided surface mesh (the level-of-detail tiles, VDTM's
/// merged surface) into a `format` target with the scans' reverse-z depth test: the
/// merged surface is seen from both sides where the scans saw it so.
pub(crate) fn surface_pipeline(
    device: &wgpu::Device,
    label: &str,
    layout: &wgpu::PipelineLayout,
    module: &wgpu::ShaderModule,
    entry_points: (&str, &str),
    vertex: wgpu::VertexBufferLayout<'_>,
    format: wgpu::TextureFormat,
) -> wgpu::RenderPipeline {
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some(label),
        layout: Some(layout),
        vertex: wgpu::VertexState {
            module,
            entry_point: Some(entry_points.0),
            compilation_options: Default::default(),
            buffers: &[Some(vertex)],
        },
        primitive: wgpu::PrimitiveState {
            topology: wgpu::PrimitiveTopology::TriangleList,
            cull_mode: None,
            ..Default::default()
        },
        depth_stencil: depth_state(),
        multisample: wgpu::MultisampleState::default(),
        fragment: Some(wgpu::FragmentState {
            module,
            entry_point: Some(entry_points.1),
            compilation_options: Default::default(),
            targets: &[replace(format)],
        }),
        multiview_mask: None,
        cache: None,
    })
}
