//! The hand on the canvas: pointer events (mouse, pen and touch alike) and the wheel,
//! listened to on the canvas and gathered as [`Gestures`].

use std::cell::RefCell;
use std::rc::Rc;

use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;
use web_sys::{HtmlCanvasElement, PointerEvent, WheelEvent};

use super::gestures::Gestures;
use super::wake::Wake;

/// The listeners, kept alive as long as the page runs.
pub struct Listeners {
    _closures: Vec<Closure<dyn FnMut(web_sys::Event)>>,
}

/// Listens on `canvas`; the gathered movement lands in `gestures`, and every event
/// wakes the frame loop (which draws only if the view changed).
pub fn listen(
    canvas: &HtmlCanvasElement,
    gestures: &Rc<RefCell<Gestures>>,
    wake: &Wake,
) -> Result<Listeners, JsValue> {
    let mut closures = Vec::new();
    let mut on = |name: &str, mut f: Box<dyn FnMut(web_sys::Event)>| -> Result<(), JsValue> {
        let wake = wake.clone();
        let closure = Closure::<dyn FnMut(web_sys::Event)>::wrap(Box::new(move |e| {
            f(e);
            wake.wake();
        }));
        canvas.add_event_listener_with_callback(name, closure.as_ref().unchecked_ref())?;
        closures.push(closure);
        Ok(())
    };
    let dpr = || web_sys::window().map_or(1.0, |w| w.device_pixel_ratio().max(0.1));
    {
        let g = Rc::clone(gestures);
        let target = canvas.clone();
        on(
            "pointerdown",
            Box::new(move |e| {
                if let Some(e) = e.dyn_ref::<PointerEvent>() {
                    let pans = e.button() != 0 || e.shift_key();
                    let _ = target.set_pointer_capture(e.pointer_id());
                    let at = (f64::from(e.client_x()), f64::from(e.client_y()));
                    g.borrow_mut().down(e.pointer_id(), at, pans);
                    e.prevent_default();
                }
            }),
        )?;
    }
    {
        let g = Rc::clone(gestures);
        on(
            "pointermove",
            Box::new(move |e| {
                if let Some(e) = e.dyn_ref::<PointerEvent>() {
                    let at = (f64::from(e.client_x()), f64::from(e.client_y()));
                    g.borrow_mut().moved(e.pointer_id(), at, dpr());
                }
            }),
        )?;
    }
    for name in ["pointerup", "pointercancel", "pointerleave"] {
        let g = Rc::clone(gestures);
        on(
            name,
            Box::new(move |e| {
                if let Some(e) = e.dyn_ref::<PointerEvent>() {
                    g.borrow_mut().up(e.pointer_id());
                }
            }),
        )?;
    }
    {
        let g = Rc::clone(gestures);
        on(
            "wheel",
            Box::new(move |e| {
                if let Some(e) = e.dyn_ref::<WheelEvent>() {
                    // Lines (mode 1) count as steps, pixels as 40 to a step (the window's
                    // scale).
                    let steps = match e.delta_mode() {
                        1 => -e.delta_y(),
                        2 => -10.0 * e.delta_y(),
                        _ => -e.delta_y() / 40.0,
                    };
                    let mut g = g.borrow_mut();
                    g.wheel(steps);
                    e.prevent_default();
                }
            }),
        )?;
    }
    on("contextmenu", Box::new(|e| e.prevent_default()))?;
    Ok(Listeners {
        _closures: closures,
    })
}
