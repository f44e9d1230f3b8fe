//! The window's events: input moves the camera and marks the view changed, and before
//! the loop waits it decides whether to draw at all (`pacing.rs`).

use web_time::Instant;
use winit::application::ApplicationHandler;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow};
use winit::keyboard::{KeyCode, PhysicalKey};
use winit::window::WindowId;

use super::{App, pacing};

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
            Some(w) => {
                let response = w.egui_state.on_window_event(&w.window, &event);
                // The overlay changed (hover, a click, a slider): draw it again.
                self.pacing.dirty |= response.repaint;
                response.consumed
            }
            None => false,
        };
        // Input that may move the camera or change what is shown.
        if matches!(
            event,
            WindowEvent::Resized(_)
                | WindowEvent::KeyboardInput { .. }
                | WindowEvent::MouseWheel { .. }
                | WindowEvent::Focused(_)
        ) || (matches!(event, WindowEvent::CursorMoved { .. }) && self.drag.is_some())
        {
            self.pacing.dirty = true;
        }
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
                        if code == KeyCode::KeyL && !event.repeat {
                            self.viewer.show_tiles = !self.viewer.show_tiles;
                        }
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

    /// Before the loop waits: take what the source sent, then ask for a redraw now,
    /// or wake at the next deadline (the settle time, the overlay's repaint, a
    /// residency step), else only to look at the source again.
    fn about_to_wait(&mut self, event_loop: &ActiveEventLoop) {
        let Some(w) = self.window.as_mut() else {
            return;
        };
        let now = Instant::now();
        if self
            .viewer
            .apply_events(&self.options.events, &mut w.renderer)
            > 0
        {
            self.pacing.dirty = true;
        }
        let flying = FLY_KEYS.iter().any(|k| self.keys.contains(k));
        // Tiles and VDTM builds change over time by themselves (loads, fades, builds
        // in the background): those frames are drawn continuously.
        let animating = self.options.screenshot.is_some()
            || w.vdtm.is_some()
            || (w.tiles.is_some() && self.viewer.show_tiles);
        let r = &self.viewer.residency_stats;
        let stepping = r.pending > r.in_flight;
        let next = self.pacing.next_redraw(now, flying || animating, stepping);
        match next {
            Some(at) if at <= now => w.window.request_redraw(),
            _ => {}
        }
        if let Some(report) = self.pacing.idle_report(now, next.is_none()) {
            println!("{report}");
            event_loop.exit();
            return;
        }
        let wake = next
            .filter(|at| *at > now)
            .unwrap_or(now + pacing::SOURCE_POLL)
            .min(now + pacing::SOURCE_POLL);
        event_loop.set_control_flow(ControlFlow::WaitUntil(wake));
    }
}

/// The keys that fly the camera while held.
const FLY_KEYS: [KeyCode; 6] = [
    KeyCode::KeyW,
    KeyCode::KeyS,
    KeyCode::KeyD,
    KeyCode::KeyA,
    KeyCode::KeyE,
    KeyCode::KeyQ,
];
