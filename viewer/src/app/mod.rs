//! The window: winit + egui over the same renderer as headless rendering. Scans arrive
//! through a channel of viewer events (a live daemon connection, an in-process
//! replay, or a loaded capture) and are uploaded as they come; the overlay shows the
//! connection, the daemon's status and the stream latency, and controls mode,
//! blending, visibility and the camera.

mod controls;
mod ui;

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::mpsc::{Receiver, SyncSender};
use std::time::Instant;

use anyhow::Context;
use texel::model::{Model, ModelEvent};
use texel::wire::Status;
use winit::application::ApplicationHandler;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::{KeyCode, PhysicalKey};
use winit::window::{Window, WindowId};

pub use controls::CameraControls;

use crate::camera::VirtualCamera;
use crate::gpu::{FrameStats, GpuContext, RenderSettings, RenderTarget, Renderer};
use crate::live::{ConnectionState, LatencyMeter, SourceCommand, ViewerEvent, fov_y_deg_of_scan};
use crate::residency::{Fetcher, Residency, ResidencyStats};

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
}

/// What the viewer shows, independent of the window.
pub struct ViewerState {
    pub model: Model,
    pub settings: RenderSettings,
    pub controls: CameraControls,
    pub fov_deg: f64,
    pub follow_newest: bool,
    pub stats: FrameStats,
    pub fps: f64,
    /// A request from the UI to jump to a scan's acquisition view.
    pub jump_to: Option<u64>,
    /// The source's connection, if it reports one.
    pub connection: Option<ConnectionState>,
    /// The daemon's latest status and when it came.
    pub status: Option<(Status, Instant)>,
    /// Whether the first snapshot is complete.
    pub snapshot_complete: bool,
    pub latency: LatencyMeter,
    /// What of the model is on the GPU, within the budget.
    pub residency: Residency,
    pub residency_stats: ResidencyStats,
    camera_placed: bool,
    fov_known: bool,
}

impl ViewerState {
    pub fn new(settings: RenderSettings, fov_deg: Option<f64>, residency: Residency) -> Self {
        Self {
            model: Model::new(),
            settings,
            controls: CameraControls::new(texel::Pose::identity(), 3.0),
            fov_deg: fov_deg.unwrap_or(50.0),
            follow_newest: false,
            stats: FrameStats::default(),
            fps: 0.0,
            jump_to: None,
            connection: None,
            status: None,
            snapshot_complete: false,
            latency: LatencyMeter::default(),
            residency_stats: residency.stats(),
            residency,
            camera_placed: false,
            fov_known: fov_deg.is_some(),
        }
    }

    /// Applies the events waiting (at most a bounded batch per frame, so the window
    /// stays responsive while a large snapshot arrives) and uploads what they bring;
    /// a bad event is reported and skipped, never fatal.
    pub fn apply_events(&mut self, events: &Receiver<ViewerEvent>, renderer: &mut Renderer) {
        const MAX_PER_FRAME: usize = 64;
        for _ in 0..MAX_PER_FRAME {
            let Ok(event) = events.try_recv() else {
                break;
            };
            let (event, received) = match event {
                ViewerEvent::Model { event, received } => (event, received),
                ViewerEvent::Reset => {
                    self.model = Model::new();
                    self.residency.reset(renderer);
                    self.snapshot_complete = false;
                    continue;
                }
                ViewerEvent::ScanUnavailable { id, reason } => {
                    self.residency.unavailable(id, reason);
                    continue;
                }
                ViewerEvent::SnapshotComplete { .. } => {
                    self.snapshot_complete = true;
                    continue;
                }
                ViewerEvent::Status { status, received } => {
                    self.status = Some((*status, received));
                    continue;
                }
                ViewerEvent::Connection(state) => {
                    self.connection = Some(state);
                    continue;
                }
            };
            self.latency.received(received);
            if let Err(e) = self.model.apply(event.clone()) {
                eprintln!("warning: model event skipped: {e}");
                continue;
            }
            // Residency uploads what the view needs at the next step.
            self.residency.observe(&event, &self.model, renderer);
            match event {
                ModelEvent::ScanAdded {
                    id,
                    scan,
                    world_from_scan,
                } => {
                    if !self.fov_known
                        && let Some(fov) = fov_y_deg_of_scan(&scan)
                    {
                        self.fov_deg = fov;
                        self.fov_known = true;
                    }
                    let newest = self.model.scans().last().is_some_and(|s| s.id == id);
                    if (self.follow_newest && newest) || !self.camera_placed {
                        self.jump(world_from_scan, median_range_m(&scan));
                    }
                }
                ModelEvent::PoseRevised {
                    id,
                    world_from_scan,
                } => {
                    // Following the sensor: the newest scan's revised pose moves the
                    // camera with it.
                    if self.follow_newest
                        && self.model.scans().last().is_some_and(|s| s.id == id)
                        && let Some(scan) = self.model.get(id).and_then(|s| s.scan.clone())
                    {
                        self.jump(world_from_scan, median_range_m(&scan));
                    }
                }
                // A model that arrives as listings first: look from the first one.
                ModelEvent::ScanListed {
                    world_from_scan,
                    listing,
                    ..
                } if !self.camera_placed => {
                    self.jump(world_from_scan, listing_range_m(&listing));
                }
                ModelEvent::ScanListed { .. }
                | ModelEvent::ScanWithdrawn { .. }
                | ModelEvent::ScanEvicted { .. } => {}
            }
        }
        if let Some(id) = self.jump_to.take()
            && let Some(s) = self.model.get(id)
        {
            let pivot = s
                .scan
                .as_deref()
                .map_or_else(|| listing_range_m(&s.listing), median_range_m);
            let pose = s.world_from_scan;
            self.jump(pose, pivot);
        }
    }

    /// Carries out residency for `camera`: evicts, uploads, fetches.
    pub fn update_residency(&mut self, renderer: &mut Renderer, camera: &VirtualCamera) {
        if self.residency.options.hidden != self.settings.hidden {
            self.residency.options.hidden = self.settings.hidden.clone();
        }
        self.residency_stats = self.residency.step(&mut self.model, renderer, camera);
    }

    /// Puts the camera at a scan's acquisition pose, pivoting `pivot_m` ahead.
    fn jump(&mut self, world_from_scan: texel::Pose, pivot_m: f64) {
        self.controls = CameraControls::new(world_from_scan, pivot_m);
        self.camera_placed = true;
    }

    pub fn camera(&self, width: u32, height: u32) -> Option<VirtualCamera> {
        VirtualCamera::new(self.controls.world_from_eo, self.fov_deg, width, height).ok()
    }
}

/// The median range (z) of a scan's vertices: where the camera pivots; 3 m for a scan
/// without a finite vertex.
fn median_range_m(scan: &texel::TexelScan) -> f64 {
    let mut ranges: Vec<f32> = scan
        .vertices
        .iter()
        .map(|v| v[2])
        .filter(|z| z.is_finite())
        .collect();
    ranges.sort_by(f32::total_cmp);
    f64::from(ranges.get(ranges.len() / 2).copied().unwrap_or(3.0))
}

/// The middle of a listing's box along its optical axis (z): the pivot before the
/// data is here; 3 m when that is not a positive finite distance.
fn listing_range_m(listing: &texel::model::ScanListing) -> f64 {
    let z = 0.5 * (f64::from(listing.bounds_min_m[2]) + f64::from(listing.bounds_max_m[2]));
    if z.is_finite() && z > 0.0 { z } else { 3.0 }
}

/// The residency of a window: fetching through `commands` when there are any, else
/// from a store of every scan that arrived.
fn window_residency(budget_bytes: u64, commands: Option<SyncSender<SourceCommand>>) -> Residency {
    let fetcher = match commands {
        Some(commands) => Fetcher::Remote { commands },
        None => Fetcher::Local {
            store: Default::default(),
        },
    };
    let mut residency = Residency::new(budget_bytes, fetcher);
    // Uploads are paced so a frame stays short while a model streams in.
    residency.max_uploads_per_step = 8;
    residency
}

struct WindowState {
    window: Arc<Window>,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    gpu: GpuContext,
    renderer: Renderer,
    egui_ctx: egui::Context,
    egui_state: egui_winit::State,
    egui_renderer: egui_wgpu::Renderer,
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
}

/// Opens the window and runs until it is closed (or the screenshot is taken).
pub fn run(options: AppOptions) -> anyhow::Result<()> {
    let event_loop = EventLoop::new().context("cannot open a window (is there a display?)")?;
    event_loop.set_control_flow(ControlFlow::Poll);
    let residency = window_residency(options.budget_bytes, options.commands.clone());
    let mut viewer = ViewerState::new(options.settings.clone(), options.fov_deg, residency);
    viewer.follow_newest = options.follow_newest;
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
        let caps = surface.get_capabilities(&gpu.adapter);
        let format = caps
            .formats
            .iter()
            .copied()
            .find(|f| !f.is_srgb())
            .or_else(|| caps.formats.first().copied())
            .context("the surface offers no format")?;
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
        Ok(WindowState {
            window,
            surface,
            config,
            gpu,
            renderer,
            egui_ctx,
            egui_state,
            egui_renderer,
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
        if dt > 0.0 {
            self.viewer.fps = 0.9 * self.viewer.fps + 0.1 / dt;
        }
        self.fly(dt.min(0.1));
        let Some(w) = self.window.as_mut() else {
            return Ok(());
        };
        self.viewer
            .apply_events(&self.options.events, &mut w.renderer);
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
        let (width, height) = (w.config.width, w.config.height);
        if let Some(camera) = self.viewer.camera(width, height) {
            self.viewer.update_residency(&mut w.renderer, &camera);
            let target = RenderTarget {
                view: &view,
                format: w.config.format,
                width,
                height,
            };
            self.viewer.stats = w.renderer.render(&camera, &self.viewer.settings, &target)?;
        }
        self.viewer.latency.drawn(Instant::now());
        // The overlay, drawn over the frame.
        let raw_input = w.egui_state.take_egui_input(&w.window);
        let viewer = &mut self.viewer;
        let roomy = width >= 700;
        let output = w
            .egui_ctx
            .run_pass(raw_input, |ctx| ui::panel(ctx, viewer, roomy));
        w.egui_state
            .handle_platform_output(&w.window, output.platform_output);
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
        w.gpu
            .queue
            .submit(extra.into_iter().chain(Some(encoder.finish())));
        for id in &textures_delta.free {
            w.egui_renderer.free_texture(id);
        }
        // Every delta is applied above.
        textures_delta.clear();
        self.frames += 1;
        if let Some((path, after, min_scans)) = &self.options.screenshot
            && self.frames >= *after
            && ((self.viewer.model.len() >= *min_scans
                && self.viewer.residency_stats.in_flight == 0
                && self.viewer.residency_stats.pending == 0)
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
        w.window.request_redraw();
        Ok(())
    }
}

/// Reads the swapchain image back as RGBA8 (BGRA formats are swizzled), opaque.
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

impl ApplicationHandler for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.window.is_some() {
            return;
        }
        match self.create_window(event_loop) {
            Ok(w) => {
                w.window.request_redraw();
                self.window = Some(w);
            }
            Err(e) => {
                self.error = Some(e);
                event_loop.exit();
            }
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _id: WindowId, event: WindowEvent) {
        let consumed = match self.window.as_mut() {
            Some(w) => w.egui_state.on_window_event(&w.window, &event).consumed,
            None => false,
        };
        match event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Resized(size) => {
                if let Some(w) = self.window.as_mut() {
                    w.config.width = size.width.max(1);
                    w.config.height = size.height.max(1);
                    w.surface.configure(&w.gpu.device, &w.config);
                }
            }
            WindowEvent::RedrawRequested => {
                if let Err(e) = self.redraw(event_loop) {
                    self.error = Some(e);
                    event_loop.exit();
                }
            }
            WindowEvent::KeyboardInput { event, .. } if !consumed => {
                if let PhysicalKey::Code(code) = event.physical_key {
                    if event.state == ElementState::Pressed {
                        self.keys.insert(code);
                    } else {
                        self.keys.remove(&code);
                    }
                }
            }
            WindowEvent::MouseInput { state, button, .. } => {
                self.drag =
                    (state == ElementState::Pressed && !consumed).then_some((button, self.cursor));
            }
            WindowEvent::CursorMoved { position, .. } => {
                self.cursor = (position.x, position.y);
                if let (Some((button, last)), Some(w)) = (self.drag, self.window.as_ref()) {
                    let (dx, dy) = (position.x - last.0, position.y - last.1);
                    let focal = self
                        .viewer
                        .camera(w.config.width, w.config.height)
                        .map_or(1000.0, |c| c.focal_px());
                    match button {
                        MouseButton::Left => self.viewer.controls.orbit(dx, dy),
                        _ => self.viewer.controls.pan(dx, dy, focal),
                    }
                    self.drag = Some((button, self.cursor));
                }
            }
            WindowEvent::MouseWheel { delta, .. } if !consumed => {
                let steps = match delta {
                    MouseScrollDelta::LineDelta(_, y) => f64::from(y),
                    MouseScrollDelta::PixelDelta(p) => p.y / 40.0,
                };
                self.viewer.controls.zoom(steps);
            }
            _ => {}
        }
    }
}
