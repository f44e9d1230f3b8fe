//! The page's start and frame loop: the link (opened first, so the daemon's snapshot
//! travels while the GPU is requested), the GPU (WebGPU where the browser offers it),
//! the canvas surface, then `requestAnimationFrame` callbacks that pump the link,
//! apply the hand's gestures, draw when the view changed and report. Frames are
//! requested only while something is under way or when an event wakes the loop
//! (`wake.rs`), so an idle page draws nothing.

mod report;

use std::cell::RefCell;
use std::rc::Rc;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};

use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;
use web_sys::HtmlCanvasElement;

use super::WEB_GPU_BUDGET_BYTES;
use super::gestures::Gestures;
use super::input::{Listeners, listen};
use super::link::Link;
use super::load::LoadMarks;
use super::page::{Page, fatal, now_ms, store_token, stored_token};
use super::wake::{Heartbeat, Wake, wake_on};
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
/// While scans stream in, a frame showing only more of the model waits until the last
/// frame's GPU work is done and at least this long has passed since, and at least
/// `STREAMING_DRAW_SHARE` times that frame's GPU time: a software renderer spends
/// 0.2 to 2 s on a full frame (on every core, for WebGPU), which the next frame with
/// more scans replaces, and which the fetches and uploads would otherwise wait for.
/// A moved camera, new settings or a resize are drawn at once.
const STREAMING_DRAW_MS: f64 = 500.0;
const STREAMING_DRAW_SHARE: f64 = 4.0;
/// How often an idle page looks at its link's clocks (silence, the retry's backoff)
/// and refreshes its status line; it draws nothing unless the view changed.
const HEARTBEAT_MS: i32 = 1000;

/// What a frame shows: the camera, the settings, the model's state (residency's
/// uploads and evictions are model events too), the canvas's size, and whether every
/// scan the view needs was there (a frame drawn once they are is the one the ready
/// signal waits for, even if the last fetches brought no model event).
type ViewKey = (
    crate::camera::VirtualCamera,
    RenderSettings,
    u64,
    (u32, u32),
    bool,
);

#[wasm_bindgen(start)]
pub fn start() {
    let wasm_ms = now_ms();
    std::panic::set_hook(Box::new(|info| {
        fatal(&format!("the viewer stopped: {info}"))
    }));
    wasm_bindgen_futures::spawn_local(async move {
        if let Err(e) = run(wasm_ms).await {
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
    /// Intervals between drawn frames that followed each other (ms), the last few.
    intervals_ms: Vec<f64>,
    /// The animation-frame time of the last drawn frame, if the last frame drew.
    last_drawn_ms: Option<f64>,
    /// When the last frame was submitted, and when the GPU finished it (`f64` bits;
    /// NaN until then): the pace while scans stream in.
    submitted_ms: f64,
    frame_done: Arc<AtomicU64>,
    /// What the last drawn frame showed.
    last_key: Option<ViewKey>,
    /// A frame is owed: deferred while scans stream in, or the surface was lost.
    owed: bool,
    /// The link or the events queue still hold messages for the next frame.
    backlog: bool,
    _heartbeat: Heartbeat,
    _on_resize: Closure<dyn FnMut()>,
    last_status_ms: f64,
    /// The mode and k of the last report, to see the controls change.
    last_controls: Option<(crate::composite::Mode, u32)>,
    complete_frames: u32,
    /// The connection (its welcome count) whose model the page last said was ready.
    ready_connection: Option<u32>,
    /// Why the last frame could not be drawn.
    draw_error: Option<String>,
    /// Where the load's time went (published in `data-texel-load`).
    load: LoadMarks,
    /// Frames drawn since the page started (`data-texel-frames`).
    frames_drawn: u64,
}

async fn run(wasm_ms: f64) -> Result<(), String> {
    let mut load = LoadMarks {
        wasm: Some(wasm_ms),
        ..Default::default()
    };
    let window = web_sys::window().ok_or("no window")?;
    let document = window.document().ok_or("no document")?;
    let wake = Wake::default();
    let page = Page::find(&document, &wake)?;
    let query = window.location().search().unwrap_or_default();
    let deep = DeepLink::parse(&query).map_err(|e| e.to_string())?;
    let canvas: HtmlCanvasElement = document
        .get_element_by_id("texel-canvas")
        .ok_or("the page has no #texel-canvas")?
        .dyn_into()
        .map_err(|_| "#texel-canvas is not a canvas")?;
    fit_canvas(&canvas);

    // The link first: the socket opens, and the daemon's snapshot arrives, while the
    // browser opens the GPU (the first frame decodes what came meanwhile).
    let location = window.location();
    let scheme = match location.protocol().as_deref() {
        Ok("https:") => "wss",
        _ => "ws",
    };
    let host = location.host().map_err(|e| format!("{e:?}"))?;
    let mut link = Link::new(
        format!("{scheme}://{host}/ws"),
        stored_token(),
        wake.clone(),
    );
    let (tx, rx) = sync_channel(EVENT_QUEUE);
    let (command_tx, commands) = sync_channel(COMMAND_QUEUE);
    link.pump(now_ms(), PUMP_BATCH, &tx, &commands);

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
    load.gpu = Some(now_ms());
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
    load.pipelines = Some(now_ms());

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
    let mut residency = window_residency(WEB_GPU_BUDGET_BYTES, Some(command_tx));
    residency.max_uploads_per_step = UPLOADS_PER_FRAME;
    // Requests answered a frame later: with long frames, more at a time (the daemon
    // allows 64 by default).
    residency.options.max_in_flight = FETCHES_IN_FLIGHT;
    let mut viewer = ViewerState::new(settings, deep.fov_deg, residency);
    if let Some(pose) = deep.pose {
        viewer.place_camera(pose, 3.0);
    }
    let gestures = Rc::new(RefCell::new(Gestures::default()));
    let listeners = listen(&canvas, &gestures, &wake).map_err(|e| format!("{e:?}"))?;
    let heartbeat = Heartbeat::start(&wake, HEARTBEAT_MS)?;
    let on_resize = wake_on(&window, "resize", &wake)?;
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
        last_drawn_ms: None,
        submitted_ms: 0.0,
        frame_done: Arc::new(AtomicU64::new(0.0_f64.to_bits())),
        last_key: None,
        owed: false,
        backlog: false,
        _heartbeat: heartbeat,
        _on_resize: on_resize,
        last_status_ms: 0.0,
        last_controls: None,
        complete_frames: 0,
        ready_connection: None,
        draw_error: None,
        load,
        frames_drawn: 0,
    }));
    animate(web, wake);
    Ok(())
}

/// Runs `frame` on an animation frame whenever `wake` asks, and on the next one for
/// as long as the frame says work is under way.
fn animate(web: Rc<RefCell<Web>>, wake: Wake) {
    let again = wake.clone();
    wake.set_callback(Closure::new(move |now: f64| {
        again.running();
        match web.borrow_mut().frame(now) {
            Ok(true) => again.wake(),
            Ok(false) => {}
            Err(e) => fatal(&e),
        }
    }));
    wake.wake();
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
    /// One frame; whether another is wanted at once (work under way).
    fn frame(&mut self, now: f64) -> Result<bool, String> {
        if fit_canvas(&self.canvas) {
            self.config.width = self.canvas.width();
            self.config.height = self.canvas.height();
            self.surface.configure(&self.gpu.device, &self.config);
        }
        // Runs the GPU's completion callbacks where the backend needs polling
        // (WebGL2); WebGPU's come by themselves.
        let _ = self.gpu.device.poll(wgpu::PollType::Poll);
        self.take_input();
        let t0 = now_ms();
        self.pump_link(now);
        let t1 = now_ms();
        let drew = self.draw()?;
        let t2 = now_ms();
        if !self.load.done() {
            self.load.pump_ms += t1 - t0;
            self.load.draw_ms += t2 - t1;
        }
        // The frame time: between drawn frames that follow each other (an idle
        // page's gaps are no frame time).
        if drew {
            if let Some(interval) = self.last_drawn_ms.map(|last| now - last)
                && interval > 0.0
            {
                if self.intervals_ms.len() >= 60 {
                    self.intervals_ms.remove(0);
                }
                self.intervals_ms.push(interval);
                self.viewer.fps = 0.9 * self.viewer.fps + 100.0 / interval;
            }
            self.last_drawn_ms = Some(now);
        } else {
            self.last_drawn_ms = None;
        }
        self.report(now, drew);
        Ok(self.busy())
    }

    /// Whether the next animation frame has work: the link connecting or waiting to
    /// retry, the snapshot or scans on their way, uploads paced over frames, messages
    /// left for the next frame, a frame owed, the ready signal still to come.
    fn busy(&self) -> bool {
        let v = &self.viewer;
        let waiting_for_token = self.link.refused();
        (!self.link.connected() && !waiting_for_token)
            || !v.snapshot_complete
            || v.residency_stats.in_flight > 0
            || v.residency_stats.pending > 0
            || self.owed
            || self.backlog
    }

    /// Whether a frame with more of the model may be drawn while scans stream in: the
    /// last one is done and the time since is long against its cost.
    fn may_draw_while_streaming(&self) -> bool {
        let done = f64::from_bits(self.frame_done.load(Ordering::Relaxed));
        if done.is_nan() {
            return false;
        }
        let cost = (done - self.submitted_ms).max(0.0);
        now_ms() - done >= (STREAMING_DRAW_SHARE * cost).max(STREAMING_DRAW_MS)
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
        self.backlog = false;
        for _ in 0..8 {
            let forwarded = self.link.pump(now, PUMP_BATCH, &self.tx, &self.commands);
            // A batch of events per call: twice covers the messages and the
            // connection events among them, so the queue never fills.
            let taken = self.viewer.apply_events(&self.rx, &mut self.renderer)
                + self.viewer.apply_events(&self.rx, &mut self.renderer);
            self.backlog = forwarded == PUMP_BATCH || taken == 2 * PUMP_BATCH;
            if forwarded < PUMP_BATCH {
                break;
            }
        }
    }

    /// Steps the residency and draws a frame if the view changed since the last one;
    /// whether one was drawn.
    fn draw(&mut self) -> Result<bool, String> {
        let (width, height) = (self.config.width, self.config.height);
        let Some(camera) = self.viewer.camera(width, height) else {
            return Ok(false);
        };
        let t0 = now_ms();
        self.viewer.update_residency(&mut self.renderer, &camera);
        if !self.load.done() {
            // (Counted in the draw's time by the caller too: taken out there.)
            let spent = now_ms() - t0;
            self.load.upload_ms += spent;
            self.load.draw_ms -= spent;
        }
        let v = &self.viewer;
        let streaming = !v.snapshot_complete
            || v.residency_stats.in_flight > 0
            || v.residency_stats.pending > 0;
        let key: ViewKey = (
            camera,
            v.settings.clone(),
            v.model.events_applied(),
            (width, height),
            !streaming,
        );
        let last = self.last_key.as_ref();
        if last == Some(&key) && !self.owed {
            return Ok(false);
        }
        let only_the_model_grew = last.is_some_and(|l| (l.0, &l.1, l.3) == (key.0, &key.1, key.3));
        if streaming && only_the_model_grew && !self.may_draw_while_streaming() {
            self.owed = true;
            return Ok(false);
        }
        let frame = match self.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(f)
            | wgpu::CurrentSurfaceTexture::Suboptimal(f) => f,
            _ => {
                self.surface.configure(&self.gpu.device, &self.config);
                self.owed = true;
                return Ok(false);
            }
        };
        self.owed = false;
        self.last_key = Some(key);
        self.submitted_ms = now_ms();
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
        let done = Arc::clone(&self.frame_done);
        done.store(f64::NAN.to_bits(), Ordering::Relaxed);
        self.gpu
            .queue
            .on_submitted_work_done(move || done.store(now_ms().to_bits(), Ordering::Relaxed));
        self.frames_drawn += 1;
        self.page.set_data("frames", &self.frames_drawn.to_string());
        Ok(true)
    }
}
