//! A full frame drawn over several submissions: the k-buffer's passes split into
//! steps (a share of the pre-pass, one batch's layers and merge, the composite), each
//! recorded and submitted on its own. A window takes one step per turn of its event
//! loop and answers input in between; a frame whose view or model changed meanwhile is
//! dropped (its steps report [`Progress::Stale`]). The finished picture is exactly
//! [`Renderer::render`]'s: the same passes in the same order.

use texel::model::ScanId;

use super::frame::Frame;
use super::kbuffer::{self, KBufferShape, Layered, PREPASS_SCANS_PER_STEP};
use super::{FrameStats, RenderSettings, RenderTarget, Renderer, Strategy, layered};
use crate::camera::VirtualCamera;
use crate::composite::Mode;
use crate::gpu::GpuError;
use crate::gpu::pipelines::OutputPipelines;
use crate::gpu::targets::DepthTarget;

/// What a step did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Progress {
    /// Submitted; more steps follow.
    Pending,
    /// The last step is submitted: the picture is in the target once the GPU is done.
    Done(FrameStats),
    /// The renderer drew another frame or its scans changed since the frame began:
    /// nothing was submitted; begin again.
    Stale,
}

/// The next step of a progressive frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Step {
    /// Not through the k-buffer (painter, naive layers, points): one step, `render`.
    Whole,
    /// The pre-pass for the visible scans from this index on.
    Prepass {
        from: usize,
    },
    /// The layers and merge of this batch.
    Batch {
        index: usize,
    },
    Composite,
    Finished,
}

/// A full frame under way (from [`Renderer::begin_progressive`]).
pub struct ProgressiveFrame {
    /// The renderer's generation it began in.
    generation: u64,
    camera: VirtualCamera,
    settings: RenderSettings,
    visible: Vec<ScanId>,
    layered: Vec<Layered>,
    batch: usize,
    step: Step,
    stats: FrameStats,
    steps_taken: usize,
}

impl ProgressiveFrame {
    pub fn camera(&self) -> &VirtualCamera {
        &self.camera
    }

    pub fn settings(&self) -> &RenderSettings {
        &self.settings
    }

    /// Steps submitted so far.
    pub fn steps_taken(&self) -> usize {
        self.steps_taken
    }

    /// Steps in all (known once the frame began).
    pub fn steps(&self) -> usize {
        match self.step {
            Step::Whole => 1,
            _ => {
                self.visible.len().div_ceil(PREPASS_SCANS_PER_STEP).max(1)
                    + self.layered.len().div_ceil(self.batch.max(1))
                    + 1
            }
        }
    }
}

impl Renderer {
    /// Begins a full frame of `camera` with `settings` for a `format` target of the
    /// camera's size, to be drawn by [`Self::step_progressive`]: culls, writes the
    /// uniforms and readies the targets; submits nothing.
    pub fn begin_progressive(
        &mut self,
        camera: &VirtualCamera,
        settings: &RenderSettings,
        format: wgpu::TextureFormat,
    ) -> Result<ProgressiveFrame, GpuError> {
        let (width, height) = (camera.width, camera.height);
        self.check_target(width, height)?;
        self.generation += 1;
        let mut job = ProgressiveFrame {
            generation: self.generation,
            camera: *camera,
            settings: settings.clone(),
            visible: Vec::new(),
            layered: Vec::new(),
            batch: 1,
            step: Step::Whole,
            stats: FrameStats::default(),
            steps_taken: 0,
        };
        let batch = match settings.strategy {
            Strategy::KBuffer { batch }
                if !settings.points && settings.composite.mode != Mode::Painter =>
            {
                batch.clamp(1, kbuffer::MAX_BATCH)
            }
            _ => return Ok(job),
        };
        let (visible, mut stats) = self.cull(camera, settings);
        self.write_uniforms(camera, settings, format, width, &visible);
        let depth = match self.depth.take() {
            Some(d) if (d.width, d.height) == (width, height) => d,
            _ => DepthTarget::new(&self.device, width, height, self.pipelines.scan_depth),
        };
        let depth_bytes = self.depth.insert(depth).bytes();
        let shape = KBufferShape {
            width,
            height,
            k: settings.composite.effective_k() as u32,
            batch,
        };
        let batches = visible.len().div_ceil(batch as usize) as u32;
        let targets = kbuffer::prepare(
            &mut self.kbuffer,
            &self.device,
            &self.pipelines,
            &self.frame_uniform,
            shape,
            batches,
        )?;
        stats.target_memory = targets.memory(depth_bytes);
        targets.marked = self.merge_marks;
        job.layered = layered(&self.scans, &visible, camera, self.layer_footprints);
        job.visible = visible;
        job.batch = batch as usize;
        job.stats = stats;
        job.step = Step::Prepass { from: 0 };
        self.nearest_ready = false;
        Ok(job)
    }

    /// Records and submits the next step of `job` into `target` (the camera's size,
    /// the format it began with); does not wait for the GPU.
    pub fn step_progressive(
        &mut self,
        job: &mut ProgressiveFrame,
        target: &RenderTarget<'_>,
    ) -> Result<Progress, GpuError> {
        if job.generation != self.generation
            || (target.width, target.height) != (job.camera.width, job.camera.height)
        {
            return Ok(Progress::Stale);
        }
        job.steps_taken += 1;
        let step = job.step;
        if step == Step::Whole {
            job.step = Step::Finished;
            let stats = self.render(&job.camera, &job.settings, target)?;
            return Ok(Progress::Done(stats));
        }
        let (Some(depth), Some(targets)) = (self.depth.as_ref(), self.kbuffer.as_mut()) else {
            return Ok(Progress::Stale);
        };
        let outputs = self
            .outputs
            .entry(target.format)
            .or_insert_with(|| OutputPipelines::new(&self.device, &self.pipelines, target.format));
        let frame = Frame {
            device: &self.device,
            queue: &self.queue,
            pipelines: &self.pipelines,
            outputs,
            frame_bind_group: &self.frame_bind_group,
            depth,
            scans: &self.scans,
            settings: &job.settings,
            target: *target,
        };
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("progressive frame step"),
            });
        let batches = job.layered.len().div_ceil(job.batch);
        let after_prepass = if batches > 0 {
            Step::Batch { index: 0 }
        } else {
            Step::Composite
        };
        job.step = match step {
            Step::Prepass { from } => {
                let to = (from + PREPASS_SCANS_PER_STEP).min(job.visible.len());
                let scans = job.visible.get(from..to).unwrap_or(&[]);
                kbuffer::encode_prepass(&frame, &mut encoder, targets, scans, from == 0);
                if to < job.visible.len() {
                    Step::Prepass { from: to }
                } else {
                    after_prepass
                }
            }
            Step::Batch { index } => {
                let from = index * job.batch;
                let to = (from + job.batch).min(job.layered.len());
                let chunk = job.layered.get(from..to).unwrap_or(&[]);
                if index == 0 {
                    kbuffer::clear_kbuffer(&mut encoder, targets);
                }
                kbuffer::encode_layers(&frame, &mut encoder, targets, index, chunk);
                kbuffer::encode_merge(&frame, &mut encoder, targets, index, chunk);
                if index + 1 < batches {
                    Step::Batch { index: index + 1 }
                } else {
                    Step::Composite
                }
            }
            Step::Composite => {
                if batches == 0 {
                    // No scan reached a layer: the k-buffer still needs emptying.
                    kbuffer::clear_kbuffer(&mut encoder, targets);
                }
                kbuffer::encode_composite(&frame, &mut encoder, targets);
                Step::Finished
            }
            Step::Whole | Step::Finished => Step::Finished,
        };
        crate::gpu::submit(&self.queue, Some(encoder.finish()));
        if job.step == Step::Finished {
            self.nearest_ready = true;
            return Ok(Progress::Done(job.stats));
        }
        Ok(Progress::Pending)
    }
}
