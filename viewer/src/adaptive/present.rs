//! The GPU side of adaptive quality: the scene rendered offscreen (RGBA8, the format
//! of headless rendering) at the interactive frame's reduced size or at full size,
//! and the pass that shows the last picture in any target (upscaled bilinearly, or
//! pixel for pixel). The full-quality picture is the one `Renderer::render_to_image`
//! gives for the same camera and settings: the same passes into the same format.

use std::collections::HashMap;

use super::{Quality, ScaleController, interactive_settings, scaled_size};
use crate::camera::VirtualCamera;
use crate::composite::Mode;
use crate::gpu::{
    FrameStats, GpuError, IMAGE_FORMAT, Progress, ProgressiveFrame, RenderSettings, RenderTarget,
    Renderer,
};

/// What the last rendered picture is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shown {
    pub quality: Quality,
    /// Its size as a fraction of the full size (1 for the full-quality frame).
    pub scale: f64,
    pub width: u32,
    pub height: u32,
    /// The mode it was drawn in.
    pub mode: Mode,
}

impl Shown {
    /// "interactive 45 % painter" or "full quality blended": what the corner shows.
    pub fn describe(&self) -> String {
        match self.quality {
            Quality::Interactive => format!(
                "interactive: {:.0} % resolution, {}",
                100.0 * self.scale,
                self.mode.name()
            ),
            Quality::Full => format!("full quality: {}", self.mode.name()),
        }
    }
}

struct Offscreen {
    texture: wgpu::Texture,
    view: wgpu::TextureView,
}

impl Offscreen {
    fn new(device: &wgpu::Device, width: u32, height: u32) -> Self {
        let texture = crate::gpu::image_texture(
            device,
            "adaptive picture",
            width,
            height,
            wgpu::TextureUsages::RENDER_ATTACHMENT
                | wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_SRC,
        );
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        Self { texture, view }
    }

    fn size(&self) -> (u32, u32) {
        (self.texture.width(), self.texture.height())
    }
}

/// The two present pipelines for one target format.
struct PresentPipelines {
    upscale: wgpu::RenderPipeline,
    exact: wgpu::RenderPipeline,
}

/// Where a refinement of the full-quality frame stands.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Refinement {
    /// A step is submitted; more follow. The picture shown is still the last one.
    Pending {
        /// Steps submitted of this frame, and in all.
        taken: usize,
        steps: usize,
    },
    /// The last step is submitted: the full-quality picture is the one shown.
    Done(FrameStats),
}

/// Renders the scene at the quality asked for into its own pictures and shows the
/// last one; holds the controller that sizes the interactive frame.
pub struct AdaptiveRenderer {
    device: wgpu::Device,
    layout: wgpu::BindGroupLayout,
    pipeline_layout: wgpu::PipelineLayout,
    module: wgpu::ShaderModule,
    sampler: wgpu::Sampler,
    pipelines: HashMap<wgpu::TextureFormat, PresentPipelines>,
    full: Option<Offscreen>,
    small: Option<Offscreen>,
    shown: Option<Shown>,
    /// The full-quality frame being refined step by step.
    pending: Option<ProgressiveFrame>,
    pub controller: ScaleController,
    /// The interactive frame's mode (blended and best frames become this; k = 1).
    pub cheap: Mode,
    /// The interactive frame draws the scans' coarse triangles.
    pub coarse: bool,
}

impl AdaptiveRenderer {
    pub fn new(device: &wgpu::Device, budget_ms: f64) -> Self {
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("present"),
            entries: &[
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
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("present"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("present"),
            source: wgpu::ShaderSource::Wgsl(
                crate::gpu::shaders::source(crate::gpu::shaders::PRESENT).into(),
            ),
        });
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("present"),
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            ..Default::default()
        });
        Self {
            device: device.clone(),
            layout,
            pipeline_layout,
            module,
            sampler,
            pipelines: HashMap::new(),
            full: None,
            small: None,
            shown: None,
            pending: None,
            controller: ScaleController::new(budget_ms),
            cheap: Mode::Painter,
            coarse: true,
        }
    }

    /// The last picture rendered, if any.
    pub fn shown(&self) -> Option<Shown> {
        self.shown
    }

    /// The full-quality picture, once one was rendered (for reading it back).
    pub fn full_texture(&self) -> Option<&wgpu::Texture> {
        self.full.as_ref().map(|o| &o.texture)
    }

    /// The interactive picture, once one was rendered (for reading it back).
    pub fn interactive_texture(&self) -> Option<&wgpu::Texture> {
        self.small.as_ref().map(|o| &o.texture)
    }

    /// Renders the scene seen by `camera` (at the full size) at `quality`: the full
    /// frame with `settings`, or the interactive one at the controller's scale with
    /// [`interactive_settings`]. Submits; does not wait.
    pub fn render(
        &mut self,
        renderer: &mut Renderer,
        camera: &VirtualCamera,
        settings: &RenderSettings,
        quality: Quality,
    ) -> Result<FrameStats, GpuError> {
        // Any frame drawn here overwrites the uniforms a refinement under way relies on.
        self.pending = None;
        let (scale, size, settings) = match quality {
            Quality::Full => (1.0, (camera.width, camera.height), settings.clone()),
            Quality::Interactive => {
                let scale = self.controller.scale();
                (
                    scale,
                    scaled_size(camera.width, camera.height, scale),
                    RenderSettings {
                        coarse: self.coarse,
                        ..interactive_settings(settings, self.cheap)
                    },
                )
            }
        };
        let mut scaled = *camera;
        (scaled.width, scaled.height) = size;
        let slot = match quality {
            Quality::Full => &mut self.full,
            Quality::Interactive => &mut self.small,
        };
        if slot.as_ref().is_none_or(|o| o.size() != size) {
            *slot = Some(Offscreen::new(&self.device, size.0, size.1));
        }
        let Some(picture) = slot.as_ref() else {
            return Err(GpuError::Readback("no picture target".into()));
        };
        let stats = renderer.render(
            &scaled,
            &settings,
            &RenderTarget {
                view: &picture.view,
                format: IMAGE_FORMAT,
                width: size.0,
                height: size.1,
            },
        )?;
        self.shown = Some(Shown {
            quality,
            scale,
            width: size.0,
            height: size.1,
            mode: settings.composite.mode,
        });
        Ok(stats)
    }

    /// Takes the next step of the full-quality frame of `camera` with `settings`, drawn
    /// over several submissions so that a window answers input between them (a
    /// software rasteriser takes seconds over a full frame): begins it when none is
    /// under way for this view, or when the one under way went stale. Submits one
    /// step; does not wait. The finished picture is [`Self::render`]'s at
    /// [`Quality::Full`].
    pub fn refine(
        &mut self,
        renderer: &mut Renderer,
        camera: &VirtualCamera,
        settings: &RenderSettings,
    ) -> Result<Refinement, GpuError> {
        let size = (camera.width, camera.height);
        if self.full.as_ref().is_none_or(|o| o.size() != size) {
            self.full = Some(Offscreen::new(&self.device, size.0, size.1));
        }
        let Some(picture) = self.full.as_ref() else {
            return Err(GpuError::Readback("no picture target".into()));
        };
        let target = RenderTarget {
            view: &picture.view,
            format: IMAGE_FORMAT,
            width: size.0,
            height: size.1,
        };
        // A stale frame (another frame drawn, or the scans changed) begins again once.
        for _ in 0..2 {
            let mut job = match self.pending.take() {
                Some(job) if job.camera() == camera && job.settings() == settings => job,
                _ => renderer.begin_progressive(camera, settings, IMAGE_FORMAT)?,
            };
            match renderer.step_progressive(&mut job, &target)? {
                Progress::Pending => {
                    let progress = Refinement::Pending {
                        taken: job.steps_taken(),
                        steps: job.steps(),
                    };
                    self.pending = Some(job);
                    return Ok(progress);
                }
                Progress::Done(stats) => {
                    self.shown = Some(Shown {
                        quality: Quality::Full,
                        scale: 1.0,
                        width: size.0,
                        height: size.1,
                        mode: settings.composite.mode,
                    });
                    return Ok(Refinement::Done(stats));
                }
                Progress::Stale => {}
            }
        }
        Err(GpuError::Readback(
            "the full-quality frame went stale as soon as it began".into(),
        ))
    }

    /// Drops the full-quality frame under way, if any (the view moved on).
    pub fn abandon_refinement(&mut self) {
        self.pending = None;
    }

    /// Whether a full-quality frame is under way.
    pub fn refining(&self) -> bool {
        self.pending.is_some()
    }

    /// Records the pass that shows the last picture in `target` (replacing what is
    /// there). Returns false when there is none yet.
    pub fn present(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        target: &RenderTarget<'_>,
    ) -> bool {
        let Some(shown) = self.shown else {
            return false;
        };
        let picture = match shown.quality {
            Quality::Full => self.full.as_ref(),
            Quality::Interactive => self.small.as_ref(),
        };
        let Some(picture) = picture else {
            return false;
        };
        let exact = picture.size() == (target.width, target.height);
        let pipelines = self.pipelines.entry(target.format).or_insert_with(|| {
            present_pipelines(
                &self.device,
                &self.pipeline_layout,
                &self.module,
                target.format,
            )
        });
        let bind_group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("present"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(&picture.view),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: wgpu::BindingResource::Sampler(&self.sampler),
                },
            ],
        });
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("present"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: target.view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(if exact {
            &pipelines.exact
        } else {
            &pipelines.upscale
        });
        pass.set_bind_group(0, &bind_group, &[]);
        pass.draw(0..3, 0..1);
        true
    }
}

fn present_pipelines(
    device: &wgpu::Device,
    layout: &wgpu::PipelineLayout,
    module: &wgpu::ShaderModule,
    format: wgpu::TextureFormat,
) -> PresentPipelines {
    let constants = [("SRGB_TARGET", if format.is_srgb() { 1.0 } else { 0.0 })];
    let pipeline = |entry: &str| {
        device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("present"),
            layout: Some(layout),
            vertex: wgpu::VertexState {
                module,
                entry_point: Some("vs_present"),
                compilation_options: Default::default(),
                buffers: &[],
            },
            primitive: wgpu::PrimitiveState::default(),
            depth_stencil: None,
            multisample: wgpu::MultisampleState::default(),
            fragment: Some(wgpu::FragmentState {
                module,
                entry_point: Some(entry),
                compilation_options: wgpu::PipelineCompilationOptions {
                    constants: &constants,
                    ..Default::default()
                },
                targets: &[Some(wgpu::ColorTargetState {
                    format,
                    blend: None,
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        })
    };
    PresentPipelines {
        upscale: pipeline("fs_upscale"),
        exact: pipeline("fs_exact"),
    }
}
