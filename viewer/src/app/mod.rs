//! The window: winit + egui over the same renderer as headless rendering. Scans arrive
//! through a channel of viewer events (a live daemon connection, an in-process
//! replay, or a loaded capture); what the view needs is uploaded within the GPU budget
//! (`state.rs`, `crate::residency`); the overlay shows the connection, the daemon's
//! status, the stream latency and the residency, and controls mode, blending,
//! visibility and the camera. Frames are paced (`pacing.rs`): drawn only when
//! something changed, cheap while the view moves, full quality once it is still
//! (`crate::adaptive`).

mod controls;
mod events;
mod pacing;
mod refine;
mod state;
mod ui;

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::mpsc::{Receiver, SyncSender};
// `web_time`: the std clock natively, the browser's in wasm (where std's panics).
use web_time::{Duration, Instant};

use anyhow::Context;
use winit::event::MouseButton;
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::KeyCode;
use winit::window::Window;

pub use controls::CameraControls;
pub use state::ViewerState;

pub(crate) use state::window_residency;

use self::refine::RefineStep;
use crate::adaptive::{Decision, Quality, Refinement};
use crate::gpu::{GpuContext, RenderSettings, RenderTarget, Renderer};
use crate::live::{SourceCommand, ViewerEvent};
use crate::tiles::net::NetTileSource;
use crate::tiles::pass::PassTarget;
use crate::tiles::{TileRenderer, TileSettings};

pub struct AppOptions {
    pub title: String,
    pub width: u32,
    pub height: u32,
    /// Vertical field of view; `None`: estimated from the first scan.
    pub fov_deg: Option<f64>,
    pub settings: RenderSettings,
    pub events: Receiver<ViewerEvent>,
    /// Where missing scans are asked for (a live source); `None`: every scan's data
    /// arrives through `events` and is kept on the CPU for re-upload.
    pub commands: Option<SyncSender<SourceCommand>>,
    /// The GPU bytes scans may hold.
    pub budget_bytes: u64,
    /// Start following the newest scan.
    pub follow_newest: bool,
    /// Read back the frame after this many frames once the model holds this many
    /// scans (or a minute has passed), write it, and exit.
    pub screenshot: Option<(PathBuf, u32, usize)>,
    /// The daemon's level-of-detail tiles, drawn instead of the scans (`L` switches).
    pub tiles: Option<NetTileSource>,
    /// With the tiles, draw the scans below the finest tiles the view finds too
    /// coarse (a check box in the panel).
    pub scans_below_tiles: bool,
    /// Draw the merged surface textured view-dependently (Debevec 1998) instead of
    /// the scans, rebuilt in the background as the model changes (the scans show
    /// until the first build is done).
    pub vdtm: Option<crate::vdtm::VdtmChoice>,
    /// The response curve that makes exposed EO frames radiance for the `points`
    /// mode's HDR rendering (sRGB when the source gives none).
    pub eo_response: Option<texel::radiance::EoResponse>,
    /// The interactive frame's budget, milliseconds, while the view moves; `None`:
    /// every frame at full quality.
    pub interactive_ms: Option<f64>,
    /// Once the full-quality frame is shown and nothing is pending, stay idle this
    /// long, print what the window submitted to the GPU meanwhile, and exit.
    pub exit_when_idle: Option<Duration>,
}

/// How often the window reads its tile depth back for the coverage feedback.
const FEEDBACK_EVERY: Duration = Duration::from_millis(200);

struct WindowState {
    window: Arc<Window>,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    gpu: GpuContext,
    renderer: Renderer,
    egui_ctx: egui::Context,
    egui_state: egui_winit::State,
    egui_renderer: egui_wgpu::Renderer,
    tiles: Option<TileRenderer<NetTileSource>>,
    /// The tile pass's depth buffer, at the surface's size.
    tile_depth: Option<(u32, u32, wgpu::TextureView)>,
    /// When the tile depth was last read back for the coverage feedback.
    last_feedback: Option<Instant>,
    vdtm: Option<crate::vdtm::LiveVdtm>,
    adaptive: crate::adaptive::AdaptiveRenderer,
}

struct App {
    options: AppOptions,
    viewer: ViewerState,
    window: Option<WindowState>,
    error: Option<anyhow::Error>,
    frames: u32,
    started: Instant,
    last_frame: Instant,
    drag: Option<(MouseButton, (f64, f64))>,
    cursor: (f64, f64),
    keys: std::collections::HashSet<KeyCode>,
    pacing: pacing::Pacing,
}

/// Opens the window and runs until it is closed (or the screenshot is taken).
pub fn run(options: AppOptions) -> anyhow::Result<()> {
    let event_loop = EventLoop::new().context("cannot open a window (is there a display?)")?;
    // Woken by input, by `about_to_wait`'s deadlines, or by a redraw it requests.
    event_loop.set_control_flow(ControlFlow::Wait);
    let residency = window_residency(options.budget_bytes, options.commands.clone());
    let mut viewer = ViewerState::new(options.settings.clone(), options.fov_deg, residency);
    viewer.follow_newest = options.follow_newest;
    let pacing = pacing::Pacing::new(options.interactive_ms.is_some(), options.exit_when_idle);
    let mut app = App {
        options,
        viewer,
        window: None,
        error: None,
        frames: 0,
        started: Instant::now(),
        last_frame: Instant::now(),
        drag: None,
        cursor: (0.0, 0.0),
        keys: Default::default(),
        pacing,
    };
    event_loop.run_app(&mut app).context("window event loop")?;
    match app.error {
        Some(e) => Err(e),
        None => Ok(()),
    }
}

impl App {
    fn create_window(&mut self, event_loop: &ActiveEventLoop) -> anyhow::Result<WindowState> {
        let attributes = Window::default_attributes()
            .with_title(self.options.title.clone())
            .with_inner_size(winit::dpi::PhysicalSize::new(
                self.options.width,
                self.options.height,
            ));
        let window = Arc::new(
            event_loop
                .create_window(attributes)
                .context("creating the window")?,
        );
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let surface = instance
            .create_surface(Arc::clone(&window))
            .context("creating the window surface")?;
        let gpu = GpuContext::with_instance(instance, Some(&surface))?;
        if gpu.adapter.get_info().device_type == wgpu::DeviceType::Cpu {
            // Said once: why the picture is coarse while it moves.
            eprintln!(
                "texel-viewer: no GPU found, drawing on the CPU with {}; {}",
                gpu.adapter_name(),
                match self.options.interactive_ms {
                    Some(ms) => format!(
                        "while the view moves, frames are drawn at a lower resolution \
                         within {ms:.0} ms, then in full once it is still"
                    ),
                    None => "every frame in full (--interactive-ms 0)".into(),
                }
            );
        }
        let caps = surface.get_capabilities(&gpu.adapter);
        let format = crate::gpu::surface_format(&caps).context("the surface offers no format")?;
        let mut usage = wgpu::TextureUsages::RENDER_ATTACHMENT;
        if caps.usages.contains(wgpu::TextureUsages::COPY_SRC) {
            usage |= wgpu::TextureUsages::COPY_SRC;
        }
        let size = window.inner_size();
        let config = wgpu::SurfaceConfiguration {
            usage,
            format,
            width: size.width.max(1),
            height: size.height.max(1),
            present_mode: wgpu::PresentMode::AutoVsync,
            desired_maximum_frame_latency: 2,
            alpha_mode: caps
                .alpha_modes
                .first()
                .copied()
                .unwrap_or(wgpu::CompositeAlphaMode::Auto),
            view_formats: vec![],
            color_space: wgpu::SurfaceColorSpace::default(),
        };
        surface.configure(&gpu.device, &config);
        let renderer = Renderer::new(&gpu);
        let egui_ctx = egui::Context::default();
        let egui_state = egui_winit::State::new(
            egui_ctx.clone(),
            egui::ViewportId::ROOT,
            &window,
            Some(window.scale_factor() as f32),
            None,
            Some(gpu.device.limits().max_texture_dimension_2d as usize),
        );
        let egui_renderer =
            egui_wgpu::Renderer::new(&gpu.device, format, egui_wgpu::RendererOptions::default());
        let tiles = match self.options.tiles.take() {
            Some(source) => {
                self.viewer.show_tiles = true;
                self.viewer.scans_below_tiles = self.options.scans_below_tiles;
                Some(TileRenderer::new(&gpu, source, TileSettings::default())?)
            }
            None => None,
        };
        let vdtm = self
            .options
            .vdtm
            .take()
            .map(|choice| crate::vdtm::LiveVdtm::new(&gpu, choice));
        let adaptive = crate::adaptive::AdaptiveRenderer::new(
            &gpu.device,
            self.options
                .interactive_ms
                .unwrap_or(crate::adaptive::DEFAULT_INTERACTIVE_MS),
        );
        Ok(WindowState {
            window,
            surface,
            config,
            gpu,
            renderer,
            egui_ctx,
            egui_state,
            egui_renderer,
            tiles,
            tile_depth: None,
            last_feedback: None,
            vdtm,
            adaptive,
        })
    }

    fn fly(&mut self, dt: f64) {
        let speed = self.viewer.controls.pivot_distance_m.max(0.5) * dt;
        let mut d = nalgebra::Vector3::zeros();
        for (key, axis) in [
            (KeyCode::KeyW, nalgebra::Vector3::z()),
            (KeyCode::KeyS, -nalgebra::Vector3::z()),
            (KeyCode::KeyD, nalgebra::Vector3::x()),
            (KeyCode::KeyA, -nalgebra::Vector3::x()),
            (KeyCode::KeyE, -nalgebra::Vector3::y()),
            (KeyCode::KeyQ, nalgebra::Vector3::y()),
        ] {
            if self.keys.contains(&key) {
                d += axis;
            }
        }
        if d != nalgebra::Vector3::zeros() {
            self.viewer.controls.fly(d * speed);
        }
    }

    fn redraw(&mut self, event_loop: &ActiveEventLoop) -> anyhow::Result<()> {
        let now = Instant::now();
        let dt = now.duration_since(self.last_frame).as_secs_f64();
        self.last_frame = now;
        self.fly(dt.min(0.1));
        let Some(w) = self.window.as_mut() else {
            return Ok(());
        };
        self.viewer
            .apply_events(&self.options.events, &mut w.renderer);
        let (width, height) = (w.config.width, w.config.height);
        let refined_here = match self.refine_without_drawing(now)? {
            RefineStep::Pending => return Ok(()),
            RefineStep::Done { began } => Some(began),
            RefineStep::NotHere => None,
        };
        let Some(w) = self.window.as_mut() else {
            return Ok(());
        };
        let frame = match w.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(f)
            | wgpu::CurrentSurfaceTexture::Suboptimal(f) => f,
            other => {
                // Lost or outdated: reconfigure and try next frame.
                let _ = other;
                w.surface.configure(&w.gpu.device, &w.config);
                return Ok(());
            }
        };
        let view = frame
            .texture
            .create_view(&wgpu::TextureViewDescriptor::default());
        let mut drawn = refined_here.map(|_| Quality::Full);
        // A step of the full-quality frame was submitted (more to come).
        let mut stepped = false;
        // When the full-quality frame finished here began (its first step).
        let mut full_began = refined_here.flatten();
        let mut through_adaptive = false;
        if let Some(camera) = self.viewer.camera(width, height) {
            let target = RenderTarget {
                view: &view,
                format: w.config.format,
                width,
                height,
            };
            let vdtm_drawn = match w.vdtm.as_mut() {
                Some(vdtm) => {
                    vdtm.update(&w.gpu, &self.viewer.model, false);
                    vdtm.settings = *self.viewer.vdtm_settings.get_or_insert(vdtm.settings);
                    self.viewer.vdtm_status = Some(vdtm.status.clone());
                    let depth = tile_depth(&w.gpu, &mut w.tile_depth, width, height);
                    let mut encoder =
                        w.gpu
                            .device
                            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                                label: Some("vdtm"),
                            });
                    let pass_target = PassTarget {
                        colour: target,
                        depth,
                        clear: Some(self.viewer.settings.composite.background),
                        scans: None,
                    };
                    let drawn = vdtm.encode(&mut encoder, &pass_target, &camera);
                    if drawn {
                        crate::gpu::submit(&w.gpu.queue, Some(encoder.finish()));
                    }
                    drawn
                }
                None => false,
            };
            match w.tiles.as_mut().filter(|_| self.viewer.show_tiles) {
                _ if vdtm_drawn => {}
                Some(tiles) => {
                    let now_s = now.duration_since(self.started).as_secs_f64();
                    tiles.settings.hybrid.enabled = self.viewer.scans_below_tiles;
                    let stats = tiles.update(&camera, now_s);
                    self.viewer.tile_stats = Some(stats);
                    // The scans below the finest tiles the view finds too coarse: only
                    // they are held (residency) and drawn beneath the tiles.
                    let wanted = tiles.scans_wanted(self.viewer.model.scans(), &camera);
                    self.viewer.settings.only = Some(wanted.clone());
                    self.viewer.update_residency(&mut w.renderer, &camera);
                    let depth = tile_depth(&w.gpu, &mut w.tile_depth, width, height);
                    let hybrid = tiles.encode_over_scans(
                        &mut w.renderer,
                        &self.viewer.settings,
                        &wanted,
                        &camera,
                        &target,
                        depth,
                    )?;
                    if let Some(scan_stats) = hybrid.scans {
                        self.viewer.stats = scan_stats;
                    }
                    // Where the tiles still showed over their scans, a few times a
                    // second: a read-back waits for the GPU.
                    let due = w
                        .last_feedback
                        .is_none_or(|t| now.duration_since(t) >= FEEDBACK_EVERY);
                    if due {
                        w.last_feedback = Some(now);
                        tiles.feed_back_coverage(
                            &w.renderer,
                            &hybrid,
                            &wanted,
                            depth.texture(),
                            &camera,
                            self.viewer.model.scans(),
                        )?;
                    }
                }
                None => {
                    self.viewer.settings.only = None;
                    if w.tiles.is_some() {
                        // Keep the tile switch in the panel while scans are drawn.
                        self.viewer.tile_stats.get_or_insert_default();
                    }
                    self.viewer.update_residency(&mut w.renderer, &camera);
                    if self.viewer.settings.points {
                        // The source's curve, else the one given, else sRGB.
                        let given = &self.options.eo_response;
                        let response = self.viewer.eo_response.get_or_insert_with(|| {
                            given
                                .clone()
                                .unwrap_or_else(texel::radiance::EoResponse::srgb)
                        });
                        let radiance = self
                            .viewer
                            .settings
                            .tone_map
                            .is_some()
                            .then_some(&*response);
                        w.renderer.prepare_points(&self.viewer.model, radiance);
                    }
                    // Through the adaptive pictures: drawn only when the view changed
                    // (cheap while it moves, full once still), shown every redraw.
                    let key = (
                        camera,
                        self.viewer.settings.clone(),
                        self.viewer.model.events_applied(),
                    );
                    let changed = self.pacing.view_changed(&key);
                    match self.pacing.pacer.decide(changed, now) {
                        Decision::Draw(Quality::Full) if self.pacing.pacer.adaptive => {
                            // The full-quality frame a step per redraw: input is read
                            // between steps, and a moved view drops the rest.
                            match w.adaptive.refine(
                                &mut w.renderer,
                                &camera,
                                &self.viewer.settings,
                            )? {
                                Refinement::Done(stats) => {
                                    full_began = self.pacing.refine_started.take();
                                    self.viewer.stats = stats;
                                    self.pacing.drawn(Quality::Full, key);
                                    drawn = Some(Quality::Full);
                                }
                                Refinement::Pending { taken, steps } => {
                                    self.pacing.refine_started.get_or_insert(now);
                                    self.viewer.refining = Some((taken, steps));
                                    stepped = true;
                                }
                            }
                        }
                        Decision::Draw(quality) => {
                            self.viewer.stats = w.adaptive.render(
                                &mut w.renderer,
                                &camera,
                                &self.viewer.settings,
                                quality,
                            )?;
                            self.pacing.drawn(quality, key);
                            drawn = Some(quality);
                        }
                        Decision::Idle | Decision::WaitUntil(_) => {}
                    }
                    if drawn.is_some() {
                        self.viewer.refining = None;
                    }
                    if drawn == Some(Quality::Interactive) {
                        self.pacing.refine_started = None;
                    }
                    through_adaptive = true;
                }
            }
        }
        self.viewer.latency.drawn(Instant::now());
        self.viewer.quality = w
            .adaptive
            .shown()
            .filter(|_| through_adaptive)
            .map(|shown| (shown, self.pacing.last_frame_ms));
        // The overlay, drawn over the frame.
        let raw_input = w.egui_state.take_egui_input(&w.window);
        let viewer = &mut self.viewer;
        let roomy = width >= 700;
        let output = w
            .egui_ctx
            .run_pass(raw_input, |ctx| ui::panel(ctx, viewer, roomy));
        w.egui_state
            .handle_platform_output(&w.window, output.platform_output);
        self.pacing.overlay_at = output
            .viewport_output
            .get(&egui::ViewportId::ROOT)
            .and_then(|v| now.checked_add(v.repaint_delay));
        let jobs = w
            .egui_ctx
            .tessellate(output.shapes, output.pixels_per_point);
        let screen = egui_wgpu::ScreenDescriptor {
            size_in_pixels: [width, height],
            pixels_per_point: output.pixels_per_point,
        };
        let mut textures_delta = output.textures_delta;
        for (id, deltas) in &textures_delta.set {
            for delta in deltas {
                w.egui_renderer
                    .update_texture(&w.gpu.device, &w.gpu.queue, *id, delta);
            }
        }
        let mut encoder = w
            .gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("overlay"),
            });
        if through_adaptive {
            let target = RenderTarget {
                view: &view,
                format: w.config.format,
                width,
                height,
            };
            w.adaptive.present(&mut encoder, &target);
        }
        let extra = w.egui_renderer.update_buffers(
            &w.gpu.device,
            &w.gpu.queue,
            &mut encoder,
            &jobs,
            &screen,
        );
        {
            let pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("overlay"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Load,
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: None,
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            let mut pass = pass.forget_lifetime();
            w.egui_renderer.render(&mut pass, &jobs, &screen);
        }
        crate::gpu::submit(
            &w.gpu.queue,
            extra.into_iter().chain(Some(encoder.finish())),
        );
        for id in &textures_delta.free {
            w.egui_renderer.free_texture(id);
        }
        // Every delta is applied above.
        textures_delta.clear();
        self.frames += 1;
        // The screenshot is of the full-quality frame, never an interactive one.
        let refined = !through_adaptive || self.pacing.pacer.settled();
        if let Some((path, after, min_scans)) = &self.options.screenshot
            && self.frames >= *after
            && ((refined
                && self.viewer.model.len() >= *min_scans
                && self.viewer.residency_stats.in_flight == 0
                && self.viewer.residency_stats.pending == 0
                && w.vdtm.as_ref().is_none_or(|v| {
                    v.status.builds > 0
                        && !v.status.building
                        && v.prepared().is_some_and(|p| p.fused.len() >= *min_scans)
                }))
                || self.started.elapsed() > std::time::Duration::from_secs(60))
        {
            let image = read_frame(&w.gpu, &frame.texture)?;
            image
                .save(path)
                .with_context(|| format!("writing {}", path.display()))?;
            println!(
                "screenshot {}: {} scans in the model, {} drawn; {}",
                path.display(),
                self.viewer.model.len(),
                self.viewer.stats.drawn,
                self.viewer.residency_stats.describe()
            );
            w.gpu.queue.present(frame);
            event_loop.exit();
            return Ok(());
        }
        w.gpu.queue.present(frame);
        self.pacing.dirty = false;
        if stepped {
            // One step at a time on the GPU: input that arrives meanwhile waits for
            // this step alone, not for the rest of the frame.
            w.gpu.wait_idle()?;
        }
        if let Some(quality) = drawn {
            // The frame time the controller steers: everything from the start of
            // this redraw to the picture being done (the GPU waited for); for a
            // full-quality frame drawn in steps, from its first step.
            w.gpu.wait_idle()?;
            let ms = full_began.unwrap_or(now).elapsed().as_secs_f64() * 1e3;
            self.pacing.last_frame_ms = ms;
            // Frames are drawn only when something changed: the rate the scene
            // could be drawn at, not how often it was.
            if ms > 0.0 {
                self.viewer.fps = 1000.0 / ms;
            }
            if quality == Quality::Interactive {
                w.adaptive.controller.observe(ms);
            }
        }
        Ok(())
    }
}

/// Reads the swapchain image back as RGBA8 (BGRA formats are swizzled), opaque.
/// The tile pass's depth buffer at `width` x `height`, made anew when the size
/// changed.
fn tile_depth<'a>(
    gpu: &GpuContext,
    held: &'a mut Option<(u32, u32, wgpu::TextureView)>,
    width: u32,
    height: u32,
) -> &'a wgpu::TextureView {
    if !matches!(held, Some((w, h, _)) if *w == width && *h == height) {
        *held = None;
    }
    let (_, _, view) = held.get_or_insert_with(|| {
        let texture = gpu.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("window tile depth"),
            size: wgpu::Extent3d {
                width,
                height,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: crate::gpu::DEPTH_FORMAT,
            // Read back for the coverage feedback.
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        (width, height, view)
    });
    view
}

fn read_frame(gpu: &GpuContext, texture: &wgpu::Texture) -> anyhow::Result<image::RgbaImage> {
    anyhow::ensure!(
        texture.usage().contains(wgpu::TextureUsages::COPY_SRC),
        "the surface cannot be read back (no COPY_SRC)"
    );
    let mut image = crate::gpu::read_rgba_texture(&gpu.device, &gpu.queue, texture)
        .context("reading the screenshot back")?;
    // The swapchain's alpha is whatever the compositor left; a screenshot is opaque.
    for p in image.pixels_mut() {
        p[3] = 255;
    }
    Ok(image)
}
