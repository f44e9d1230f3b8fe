//! The point proxy's long-lived GPU state (`points.wgsl`, `points_fill.wgsl`): bind
//! group layouts, the splat, scatter and colour pipelines, the pull-push compute
//! pipelines, and the output pipeline per target format.

use std::collections::HashMap;

use super::super::pipelines::{
    D2, UNFILTERED, depth_state, module, replace, storage_entry, texture_entry, uniform_entry,
};
use super::super::shaders;
use super::super::tonemap::RADIANCE_FORMAT;
use crate::points::cloud::ScanPoint;

/// The depth of the splats in pass 1, the front and back images of pass 2 and the
/// filled depth map: view-frame z (m) as f32 bits, 0 where nothing is (an integer
/// format: 32-bit float ones are not colour-renderable on every backend).
pub const POINT_DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::R32Uint;
/// Pass 1's nearest splat normal and the colour pass's weighted sums: half floats,
/// renderable and blendable everywhere.
pub const POINT_NORMAL_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;
pub const POINT_ACCUMULATION_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;

pub(crate) const POINT_ATTRIBUTES: [wgpu::VertexAttribute; 5] = wgpu::vertex_attr_array![
    0 => Float32x3, 1 => Float32, 2 => Float32x3, 3 => Float32, 4 => Float32x2
];

fn point_buffer(step_mode: wgpu::VertexStepMode) -> wgpu::VertexBufferLayout<'static> {
    wgpu::VertexBufferLayout {
        array_stride: std::mem::size_of::<ScanPoint>() as u64,
        step_mode,
        attributes: &POINT_ATTRIBUTES,
    }
}

pub(crate) struct PointsPipelines {
    /// group 1 of the render pipelines: the view (intrinsics, class), and the
    /// accumulated colours for the output pass.
    pub view_layout: wgpu::BindGroupLayout,
    pub output_layout: wgpu::BindGroupLayout,
    /// group 2: one scan's points uniform, EO image, sampler, acquisition depth map.
    pub scan_layout: wgpu::BindGroupLayout,
    /// group 3: pass 1's depth and normal, the filled depth map.
    pub targets_layout: wgpu::BindGroupLayout,
    /// The pull-push compute passes' one group.
    pub fill_layout: wgpu::BindGroupLayout,
    pub sampler: wgpu::Sampler,
    module: wgpu::ShaderModule,
    output_pipeline_layout: wgpu::PipelineLayout,
    pub splat_depth: wgpu::RenderPipeline,
    pub splat_depth_normal: wgpu::RenderPipeline,
    pub scatter: wgpu::RenderPipeline,
    pub colour: wgpu::RenderPipeline,
    pub fill_load: wgpu::ComputePipeline,
    pub fill_pull: wgpu::ComputePipeline,
    pub fill_push: wgpu::ComputePipeline,
    pub fill_resolve: wgpu::ComputePipeline,
    outputs: HashMap<wgpu::TextureFormat, wgpu::RenderPipeline>,
    /// The output as radiance (`RADIANCE_FORMAT`), for tone mapping.
    pub radiance_output: wgpu::RenderPipeline,
}

struct RenderPipelineSpec<'a> {
    label: &'a str,
    layout: &'a wgpu::PipelineLayout,
    vertex_entry: &'a str,
    buffers: &'a [Option<wgpu::VertexBufferLayout<'a>>],
    topology: wgpu::PrimitiveTopology,
    depth: bool,
    fragment_entry: &'a str,
    targets: &'a [Option<wgpu::ColorTargetState>],
}

fn render_pipeline(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    spec: RenderPipelineSpec<'_>,
) -> wgpu::RenderPipeline {
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some(spec.label),
        layout: Some(spec.layout),
        vertex: wgpu::VertexState {
            module,
            entry_point: Some(spec.vertex_entry),
            compilation_options: Default::default(),
            buffers: spec.buffers,
        },
        primitive: wgpu::PrimitiveState {
            topology: spec.topology,
            ..Default::default()
        },
        depth_stencil: if spec.depth { depth_state() } else { None },
        multisample: wgpu::MultisampleState::default(),
        fragment: Some(wgpu::FragmentState {
            module,
            entry_point: Some(spec.fragment_entry),
            compilation_options: Default::default(),
            targets: spec.targets,
        }),
        multiview_mask: None,
        cache: None,
    })
}

impl PointsPipelines {
    /// `frame_layout` and `sampler` are the renderer's (the frame uniform, the EO
    /// images' bilinear sampler).
    pub fn new(
        device: &wgpu::Device,
        frame_layout: &wgpu::BindGroupLayout,
        sampler: &wgpu::Sampler,
    ) -> Self {
        let vf = wgpu::ShaderStages::VERTEX | wgpu::ShaderStages::FRAGMENT;
        let fs = wgpu::ShaderStages::FRAGMENT;
        let cs = wgpu::ShaderStages::COMPUTE;
        let layout = |label: &str, entries: &[wgpu::BindGroupLayoutEntry]| {
            device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some(label),
                entries,
            })
        };
        let view_layout = layout("points view", &[uniform_entry(0, vf, false)]);
        let output_layout = layout("points output", &[texture_entry(1, fs, UNFILTERED, D2)]);
        let depth_map = wgpu::TextureSampleType::Uint;
        let scan_layout = layout(
            "points scan",
            &[
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
                texture_entry(3, fs, depth_map, D2),
            ],
        );
        let targets_layout = layout(
            "points targets",
            &[
                texture_entry(0, fs, depth_map, D2),
                texture_entry(1, fs, UNFILTERED, D2),
                texture_entry(2, fs, depth_map, D2),
            ],
        );
        let fill_layout = layout(
            "points fill",
            &[
                storage_entry(0, cs, false),
                uniform_entry(1, cs, true),
                texture_entry(2, cs, depth_map, D2),
                texture_entry(3, cs, depth_map, D2),
                texture_entry(4, cs, depth_map, D2),
                wgpu::BindGroupLayoutEntry {
                    binding: 5,
                    visibility: cs,
                    ty: wgpu::BindingType::StorageTexture {
                        access: wgpu::StorageTextureAccess::WriteOnly,
                        format: POINT_DEPTH_FORMAT,
                        view_dimension: D2,
                    },
                    count: None,
                },
            ],
        );
        let module = module(device, "points", shaders::POINTS);
        let fill_module =
            super::super::pipelines::module(device, "points fill", shaders::POINTS_FILL);
        let pipeline_layout = |label: &str, groups: &[Option<&wgpu::BindGroupLayout>]| {
            device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some(label),
                bind_group_layouts: groups,
                immediate_size: 0,
            })
        };
        let splat_layout = pipeline_layout(
            "points splat",
            &[Some(frame_layout), Some(&view_layout), Some(&scan_layout)],
        );
        let full_layout = pipeline_layout(
            "points colour",
            &[
                Some(frame_layout),
                Some(&view_layout),
                Some(&scan_layout),
                Some(&targets_layout),
            ],
        );
        let output_pipeline_layout =
            pipeline_layout("points output", &[Some(frame_layout), Some(&output_layout)]);
        let instance = [Some(point_buffer(wgpu::VertexStepMode::Instance))];
        let per_vertex = [Some(point_buffer(wgpu::VertexStepMode::Vertex))];
        let depth_target = [replace(POINT_DEPTH_FORMAT)];
        let splat = |label, entry, targets| {
            render_pipeline(
                device,
                &module,
                RenderPipelineSpec {
                    label,
                    layout: &splat_layout,
                    vertex_entry: "vs_splat",
                    buffers: &instance,
                    topology: wgpu::PrimitiveTopology::TriangleList,
                    depth: true,
                    fragment_entry: entry,
                    targets,
                },
            )
        };
        let splat_depth = splat("points splat", "fs_splat_depth", &depth_target);
        let splat_depth_normal = splat(
            "points splat with normals",
            "fs_splat_depth_normal",
            &[replace(POINT_DEPTH_FORMAT), replace(POINT_NORMAL_FORMAT)],
        );
        let scatter = render_pipeline(
            device,
            &module,
            RenderPipelineSpec {
                label: "points scatter",
                layout: &full_layout,
                vertex_entry: "vs_scatter",
                buffers: &per_vertex,
                topology: wgpu::PrimitiveTopology::PointList,
                depth: true,
                fragment_entry: "fs_scatter",
                targets: &depth_target,
            },
        );
        let additive = wgpu::BlendComponent {
            src_factor: wgpu::BlendFactor::One,
            dst_factor: wgpu::BlendFactor::One,
            operation: wgpu::BlendOperation::Add,
        };
        let colour = render_pipeline(
            device,
            &module,
            RenderPipelineSpec {
                label: "points colour",
                layout: &full_layout,
                vertex_entry: "vs_fullscreen",
                buffers: &[],
                topology: wgpu::PrimitiveTopology::TriangleList,
                depth: false,
                fragment_entry: "fs_colour",
                targets: &[Some(wgpu::ColorTargetState {
                    format: POINT_ACCUMULATION_FORMAT,
                    blend: Some(wgpu::BlendState {
                        color: additive,
                        alpha: additive,
                    }),
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            },
        );
        let fill_pipeline_layout = pipeline_layout("points fill", &[Some(&fill_layout)]);
        let compute = |entry: &str| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: Some(&fill_pipeline_layout),
                module: &fill_module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let radiance_output = super::super::pipelines::fullscreen_pipeline(
            device,
            &output_pipeline_layout,
            &module,
            "points radiance output",
            "fs_points_radiance",
            RADIANCE_FORMAT,
        );
        Self {
            radiance_output,
            fill_load: compute("cs_load"),
            fill_pull: compute("cs_pull"),
            fill_push: compute("cs_push"),
            fill_resolve: compute("cs_resolve"),
            view_layout,
            output_layout,
            scan_layout,
            targets_layout,
            fill_layout,
            sampler: sampler.clone(),
            module,
            output_pipeline_layout,
            splat_depth,
            splat_depth_normal,
            scatter,
            colour,
            outputs: HashMap::new(),
        }
    }

    /// The output pass into a target of `format`, built on first use.
    pub fn output(
        &mut self,
        device: &wgpu::Device,
        format: wgpu::TextureFormat,
    ) -> &wgpu::RenderPipeline {
        let (module, layout) = (&self.module, &self.output_pipeline_layout);
        self.outputs.entry(format).or_insert_with(|| {
            super::super::pipelines::fullscreen_pipeline(
                device,
                layout,
                module,
                "points output",
                "fs_points_output",
                format,
            )
        })
    }
}
