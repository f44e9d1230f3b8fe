//! Waking the page's frame loop: an animation frame is requested only when something
//! may have changed (the hand, a message from the daemon, the controls, a resize, a
//! heartbeat for the link's clocks) or while work is under way, so an idle page runs
//! no frame and submits nothing to the GPU.

use std::cell::{Cell, RefCell};
use std::rc::Rc;

use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;

/// The animation-frame callback (its argument: the frame's time in ms).
pub type FrameCallback = Closure<dyn FnMut(f64)>;

#[derive(Default)]
struct Inner {
    /// A frame is requested and has not run yet: waking again changes nothing.
    scheduled: Cell<bool>,
    callback: RefCell<Option<FrameCallback>>,
}

/// A handle that requests the next animation frame; cloned into every event listener.
#[derive(Clone, Default)]
pub struct Wake {
    inner: Rc<Inner>,
}

impl Wake {
    /// The frame callback the wakes request (set once, when the page is up).
    pub fn set_callback(&self, callback: FrameCallback) {
        *self.inner.callback.borrow_mut() = Some(callback);
    }

    /// Requests an animation frame unless one is already on its way.
    pub fn wake(&self) {
        if self.inner.scheduled.get() {
            return;
        }
        let Some(window) = web_sys::window() else {
            return;
        };
        if let Some(callback) = self.inner.callback.borrow().as_ref()
            && window
                .request_animation_frame(callback.as_ref().unchecked_ref())
                .is_ok()
        {
            self.inner.scheduled.set(true);
        }
    }

    /// The requested frame runs: the next wake requests another.
    pub fn running(&self) {
        self.inner.scheduled.set(false);
    }
}

/// Wakes the loop every `period_ms` for as long as it is kept: the link's clocks
/// (silence, the retry's backoff) and the status line's daemon figures move without
/// any event on the page.
pub struct Heartbeat {
    window: web_sys::Window,
    id: i32,
    _closure: Closure<dyn FnMut()>,
}

impl Heartbeat {
    pub fn start(wake: &Wake, period_ms: i32) -> Result<Self, String> {
        let window = web_sys::window().ok_or("no window")?;
        let wake = wake.clone();
        let closure = Closure::<dyn FnMut()>::new(move || wake.wake());
        let id = window
            .set_interval_with_callback_and_timeout_and_arguments_0(
                closure.as_ref().unchecked_ref(),
                period_ms,
            )
            .map_err(|e| format!("no timer: {e:?}"))?;
        Ok(Self {
            window,
            id,
            _closure: closure,
        })
    }
}

impl Drop for Heartbeat {
    fn drop(&mut self) {
        self.window.clear_interval_with_handle(self.id);
    }
}

/// Wakes on `name` events of `target` (a resize of the window, a control's change);
/// the listener lives as long as the returned closure.
pub fn wake_on(
    target: &web_sys::EventTarget,
    name: &str,
    wake: &Wake,
) -> Result<Closure<dyn FnMut()>, String> {
    let wake = wake.clone();
    let closure = Closure::<dyn FnMut()>::new(move || wake.wake());
    target
        .add_event_listener_with_callback(name, closure.as_ref().unchecked_ref())
        .map_err(|e| format!("cannot listen to {name}: {e:?}"))?;
    Ok(closure)
}
