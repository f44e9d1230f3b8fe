//! The page's start and frame loop: the GPU (WebGPU where the browser offers it), the
//! canvas surface, the link, then one `requestAnimationFrame` callback per frame that
//! pumps the link, applies the hand's gestures, renders and reports.

use std::cell::RefCell;
use std::rc::Rc;
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};

use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;
use web_sys::HtmlCanvasElement;

use super::gestures::Gestures;
use super::input::{Listeners, listen};
use super::link::Link;
use super::page::{Page, fatal, now_ms, store_token, stored_token};
use super::{WEB_GPU_BUDGET_BYTES, view_query};
use crate::app::{ViewerState, window_residency};
use crate::deep_link::DeepLink;
use crate::display_mode::DisplayMode;
use crate::gpu::{GpuContext, RenderSettings, RenderTarget, Renderer};
use crate::live::{COMMAND_QUEUE, EVENT_QUEUE, SourceCommand, ViewerEvent};

/// Messages decoded per pump: below the event queue, so forwarding never blocks.
const PUMP_BATCH: usize = 64;
/// Frames drawn with the whole model before the page says it is ready: the first
/// such frame is the first full view (its uploads precede its draw).
const READY_AFTER_FRAMES: u32 = 1;
/// Scans uploaded per frame. The window paces uploads at 8 so a frame stays short
/// while a model streams in; a software-rendered page spends far more on each frame
/// than on an upload, so it takes more at a time and reaches the whole model in
/// fewer frames.
const UPLOADS_PER_FRAME: usize = 32;
/// Scans requested and not yet received.
const FETCHES_IN_FLIGHT: usize = 16;

#[wasm_bindgen(start)]
pub fn start() {
    std::panic::set_hook(Box::new(|info| {
        fatal(&format!("the viewer stopped: {info}"))
    }));
    wasm_bindgen_futures::spawn_local(async {
        if let Err(e) = run().await {
            fatal(&e);
        }
    });
}

struct Web {
    page: Page,
    canvas: HtmlCanvasElement,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    gpu: GpuContext,
    renderer: Renderer,
    viewer: ViewerState,
    link: Link,
    tx: SyncSender<ViewerEvent>,
    rx: Receiver<ViewerEvent>,
    commands: Receiver<SourceCommand>,
    gestures: Rc<RefCell<Gestures>>,
    _listeners: Listeners,
    deep: DeepLink,
    path: String,
    /// Intervals between frames (ms), the last few.
    intervals_ms: Vec<f64>,
    last_frame_ms: f64,
    last_status_ms: f64,
    /// The mode and k of the last report, to see the controls change.
    last_controls: Option<(crate::composite::Mode, u32)>,
    complete_frames: u32,
    /// The connection (its welcome count) whose model the page last said was ready.
    ready_connection: Option<u32>,
    /// Why the last frame could not be drawn.
    draw_error: Option<String>,
    /// Whether the snapshot's end and full residency were marked on the page.
    marks: (bool, bool),
}

async fn run() -> Result<(), String> {
    let window = web_sys::window().ok_or("no window")?;
    let document = window.document().ok_or("no document")?;
    let page = Page::find(&document)?;
    let query = window.location().search().unwrap_or_default();
    let deep = DeepLink::parse(&query).map_err(|e| e.to_string())?;
    let canvas: HtmlCanvasElement = document
        .get_element_by_id("texel-canvas")
        .ok_or("the page has no #texel-canvas")?
        .dyn_into()
        .map_err(|_| "#texel-canvas is not a canvas")?;
    fit_canvas(&canvas);

    // WebGPU where the browser offers it, WebGL2 otherwise (`?backend=webgl2` forces it).
    let mut descriptor = wgpu::InstanceDescriptor::new_without_display_handle();
    if query.contains("backend=webgl2") {
        descriptor.backends = wgpu::Backends::GL;
    }
    let instance = wgpu::util::new_instance_with_webgpu_detection(descriptor).await;
    let surface = instance
        .create_surface(wgpu::SurfaceTarget::Canvas(canvas.clone()))
        .map_err(|e| format!("cannot draw into the canvas: {e}"))?;
    let gpu = GpuContext::request(instance, Some(&surface))
        .await
        .map_err(|e| format!("no GPU for the viewer: {e}"))?;
    let info = gpu.adapter.get_info();
    let api = match info.backend {
        wgpu::Backend::BrowserWebGpu => "WebGPU".to_string(),
        wgpu::Backend::Gl => "WebGL2".to_string(),
        other => format!("{other:?}"),
    };
    // Browsers often hide the adapter's name.
    let path = match info.name.trim() {
        "" => api,
        name => format!("{api} ({name})"),
    };
    // The k-buffer keeps each pixel's best fragments in storage buffers, which WebGL2
    // lacks: there every visible scan gets a layer of a texture array (the naive
    // layers: the same ranking and blend per pixel, memory growing with the scans in
    // view, refused by name past the device's layer limit).
    let naive = gpu.device.limits().max_storage_buffers_per_shader_stage == 0;
    let path = if naive {
        format!(
            "{path} · naive layers (no storage buffers; up to {} scans in view)",
            gpu.device.limits().max_texture_array_layers
        )
    } else {
        format!("{path} · k-buffer")
    };
    page.show_path(&path);
    page.set_data("path", &path);
    let config = surface_config(&surface, &gpu, &canvas)?;
    surface.configure(&gpu.device, &config);
    let renderer = Renderer::new(&gpu);

    let mut settings = RenderSettings::default();
    if naive {
        settings.strategy = crate::gpu::Strategy::NaiveLayers;
    }
    match deep.mode {
        Some(DisplayMode::Scans(m)) => settings.composite.mode = m,
        Some(other) => page.show_status(&format!(
            "the {other} mode is not drawn in the browser yet; showing blended"
        )),
        None => {}
    }
    if let Some(k) = deep.k {
        settings.composite.k = k;
    }
    page.set_mode(settings.composite.mode);
    page.set_k(settings.composite.k);
    let (tx, rx) = sync_channel(EVENT_QUEUE);
    let (command_tx, commands) = sync_channel(COMMAND_QUEUE);
    let mut residency = window_residency(WEB_GPU_BUDGET_BYTES, Some(command_tx));
    residency.max_uploads_per_step = UPLOADS_PER_FRAME;
    // Requests answered a frame later: with long frames, more at a time (the daemon
    // allows 64 by default).
    residency.options.max_in_flight = FETCHES_IN_FLIGHT;
    let mut viewer = ViewerState::new(settings, deep.fov_deg, residency);
    if let Some(pose) = deep.pose {
        viewer.place_camera(pose, 3.0);
    }
    let location = window.location();
    let scheme = match location.protocol().as_deref() {
        Ok("https:") => "wss",
        _ => "ws",
    };
    let host = location.host().map_err(|e| format!("{e:?}"))?;
    let link = Link::new(format!("{scheme}://{host}/ws"), stored_token());
    let gestures = Rc::new(RefCell::new(Gestures::default()));
    let listeners = listen(&canvas, &gestures).map_err(|e| format!("{e:?}"))?;
    let web = Rc::new(RefCell::new(Web {
        page,
        canvas,
        surface,
        config,
        gpu,
        renderer,
        viewer,
        link,
        tx,
        rx,
        commands,
        gestures,
        _listeners: listeners,
        deep,
        path,
        intervals_ms: Vec::new(),
        last_frame_ms: now_ms(),
        last_status_ms: 0.0,
        last_controls: None,
        complete_frames: 0,
        ready_connection: None,
        marks: (false, false),
        draw_error: None,
    }));
    animate(web);
    Ok(())
}

/// The animation-frame callback (its argument: the frame's time in ms).
type FrameCallback = Closure<dyn FnMut(f64)>;

/// Runs `frame` on every animation frame for as long as the page lives.
fn animate(web: Rc<RefCell<Web>>) {
    let callback: Rc<RefCell<Option<FrameCallback>>> = Rc::new(RefCell::new(None));
    let again = Rc::clone(&callback);
    *callback.borrow_mut() = Some(Closure::new(move |now: f64| {
        if let Err(e) = web.borrow_mut().frame(now) {
            fatal(&e);
            return;
        }
        if let Some(cb) = again.borrow().as_ref() {
            request_frame(cb);
        }
    }));
    if let Some(cb) = callback.borrow().as_ref() {
        request_frame(cb);
    }
}

fn request_frame(callback: &Closure<dyn FnMut(f64)>) {
    if let Some(window) = web_sys::window() {
        let _ = window.request_animation_frame(callback.as_ref().unchecked_ref());
    }
}

/// Sizes the canvas's drawing buffer to its displayed size in device pixels.
fn fit_canvas(canvas: &HtmlCanvasElement) -> bool {
    let dpr = web_sys::window().map_or(1.0, |w| w.device_pixel_ratio().clamp(0.5, 4.0));
    let width = ((f64::from(canvas.client_width()) * dpr).round() as u32).clamp(1, 8192);
    let height = ((f64::from(canvas.client_height()) * dpr).round() as u32).clamp(1, 8192);
    if canvas.width() != width || canvas.height() != height {
        canvas.set_width(width);
        canvas.set_height(height);
        return true;
    }
    false
}

fn surface_config(
    surface: &wgpu::Surface<'static>,
    gpu: &GpuContext,
    canvas: &HtmlCanvasElement,
) -> Result<wgpu::SurfaceConfiguration, String> {
    let caps = surface.get_capabilities(&gpu.adapter);
    let format = crate::gpu::surface_format(&caps).ok_or("the canvas offers no format")?;
    Ok(wgpu::SurfaceConfiguration {
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
        format,
        width: canvas.width().max(1),
        height: canvas.height().max(1),
        present_mode: wgpu::PresentMode::AutoVsync,
        desired_maximum_frame_latency: 2,
        // Opaque: the passes leave alpha as they please (the window's read-back
        // forces it to 1), and a premultiplied canvas would show that.
        alpha_mode: if caps.alpha_modes.contains(&wgpu::CompositeAlphaMode::Opaque) {
            wgpu::CompositeAlphaMode::Opaque
        } else {
            caps.alpha_modes
                .first()
                .copied()
                .unwrap_or(wgpu::CompositeAlphaMode::Auto)
        },
        view_formats: vec![],
        color_space: wgpu::SurfaceColorSpace::default(),
    })
}

impl Web {
    fn frame(&mut self, now: f64) -> Result<(), String> {
        let interval = now - self.last_frame_ms;
        self.last_frame_ms = now;
        if interval > 0.0 {
            if self.intervals_ms.len() >= 60 {
                self.intervals_ms.remove(0);
            }
            self.intervals_ms.push(interval);
            self.viewer.fps = 0.9 * self.viewer.fps + 100.0 / interval;
        }
        if fit_canvas(&self.canvas) {
            self.config.width = self.canvas.width();
            self.config.height = self.canvas.height();
            self.surface.configure(&self.gpu.device, &self.config);
        }
        self.take_input();
        self.pump_link(now);
        self.draw()?;
        self.report(now);
        Ok(())
    }

    /// The controls and the hand.
    fn take_input(&mut self) {
        if let Some(token) = self.page.take_token() {
            store_token(&token);
            self.link.set_token(token);
        }
        self.page.ask_token(self.link.refused());
        let composite = &mut self.viewer.settings.composite;
        composite.mode = self.page.mode();
        if let Some(k) = self.page.k() {
            composite.k = k;
        }
        let focal = self
            .viewer
            .camera(self.config.width, self.config.height)
            .map_or(1000.0, |c| c.focal_px());
        self.gestures
            .borrow_mut()
            .apply(&mut self.viewer.controls, focal);
    }

    /// Decodes what arrived and applies it, a bounded amount per frame.
    fn pump_link(&mut self, now: f64) {
        for _ in 0..8 {
            let forwarded = self.link.pump(now, PUMP_BATCH, &self.tx, &self.commands);
            // A batch of events per call: twice covers the messages and the
            // connection events among them, so the queue never fills.
            self.viewer.apply_events(&self.rx, &mut self.renderer);
            self.viewer.apply_events(&self.rx, &mut self.renderer);
            if forwarded < PUMP_BATCH {
                break;
            }
        }
    }

    fn draw(&mut self) -> Result<(), String> {
        let (width, height) = (self.config.width, self.config.height);
        let Some(camera) = self.viewer.camera(width, height) else {
            return Ok(());
        };
        self.viewer.update_residency(&mut self.renderer, &camera);
        let frame = match self.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(f)
            | wgpu::CurrentSurfaceTexture::Suboptimal(f) => f,
            _ => {
                self.surface.configure(&self.gpu.device, &self.config);
                return Ok(());
            }
        };
        let view = frame
            .texture
            .create_view(&wgpu::TextureViewDescriptor::default());
        let target = RenderTarget {
            view: &view,
            format: self.config.format,
            width,
            height,
        };
        match self
            .renderer
            .render(&camera, &self.viewer.settings, &target)
        {
            Ok(stats) => {
                self.viewer.stats = stats;
                self.draw_error = None;
            }
            // Kept in the status line until a frame draws again (too many scans in
            // view for the naive layers, a target over the device's limits).
            Err(e) => self.draw_error = Some(e.to_string()),
        }
        self.viewer.latency.drawn(web_time::Instant::now());
        self.gpu.queue.present(frame);
        Ok(())
    }

    /// The status line a few times a second, the deep link of the view, and the
    /// ready signal once the model asked for is on screen.
    fn report(&mut self, now: f64) {
        let v = &self.viewer;
        let settled = v.residency_stats.in_flight == 0 && v.residency_stats.pending == 0;
        let complete = v.snapshot_complete && settled && !v.model.is_empty();
        self.complete_frames = if complete {
            self.complete_frames.saturating_add(1)
        } else {
            0
        };
        // Where a load's time goes: the snapshot's end, then every scan of the view
        // resident (once per page).
        if v.snapshot_complete && !self.marks.0 {
            self.marks.0 = true;
            self.page.set_data("snapshot-ms", &format!("{now:.0}"));
        }
        if complete && !self.marks.1 {
            self.marks.1 = true;
            self.page.set_data("resident-ms", &format!("{now:.0}"));
        }
        let wanted = self.deep.ready_scans.unwrap_or(1);
        let connection = self.link.welcomes;
        if self.ready_connection.is_some_and(|c| c != connection) {
            // A new connection's snapshot: ready again once it is on screen.
            self.ready_connection = None;
            self.page.remove_data("ready");
        }
        if self.ready_connection.is_none()
            && self.complete_frames >= READY_AFTER_FRAMES
            && v.model.len() >= wanted
        {
            self.ready_connection = Some(connection);
            self.page.set_data("ready-ms", &format!("{now:.0}"));
            self.page.set_data("ready", &v.model.len().to_string());
            self.page
                .set_data("ready-connection", &connection.to_string());
        }
        if now - self.last_status_ms < 250.0 {
            return;
        }
        self.last_status_ms = now;
        let mut sorted = self.intervals_ms.clone();
        sorted.sort_by(f64::total_cmp);
        let median_ms = sorted.get(sorted.len() / 2).copied().unwrap_or(0.0);
        let connection = v
            .connection
            .as_ref()
            .map_or_else(|| "starting".to_string(), |c| c.describe());
        let daemon = v.status.as_ref().map_or_else(String::new, |(s, _)| {
            format!(" · daemon up {:.0} s, {} viewers", s.uptime_s, s.clients)
        });
        let error = self
            .draw_error
            .as_ref()
            .map_or_else(String::new, |e| format!(" · cannot draw: {e}"));
        self.page.show_status(&format!(
            "{connection}{daemon} · {} scans, {} drawn · {median_ms:.0} ms a frame · {}{error}",
            v.model.len(),
            v.stats.drawn,
            v.residency_stats.describe()
        ));
        self.page.set_data("scans", &v.model.len().to_string());
        self.page.set_data("drawn", &v.stats.drawn.to_string());
        self.page.set_data("frame-ms", &format!("{median_ms:.2}"));
        self.page
            .set_data("bytes", &self.link.bytes_received.to_string());
        self.page
            .set_data("connections", &self.link.welcomes.to_string());
        self.page.show_path(&self.path);
        // The address bar keeps the view, so it can be copied as a link.
        let query = view_query(
            v.settings.composite.mode,
            v.settings.composite.k,
            &v.controls.world_from_eo,
            v.fov_deg,
        );
        // (Only the hand or the controls rewrite it: the link the page was opened
        // with stays until the user changes the view.)
        let touched = std::mem::take(&mut self.gestures.borrow_mut().touched);
        let controls = (v.settings.composite.mode, v.settings.composite.k);
        let controls_changed = self.last_controls.is_some_and(|c| c != controls);
        self.last_controls = Some(controls);
        if touched || controls_changed {
            self.page.set_query(&query);
        }
    }
}
