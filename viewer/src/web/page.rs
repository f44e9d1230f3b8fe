//! The page around the canvas (`viewer/web/index.html`): the status line, the label
//! of the rendering path, the mode and blend controls, the token box shown only when
//! the daemon refuses, the address bar kept as a deep link to the current view, and
//! the ready signal a watcher (a test, a kiosk script) waits for.

use std::cell::RefCell;
use std::rc::Rc;

use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;
use web_sys::{Document, Element, HtmlElement, HtmlInputElement, HtmlSelectElement};

use super::wake::{Wake, wake_on};
use crate::composite::Mode;
use crate::display_mode::DisplayMode;

pub struct Page {
    document: Document,
    status: Element,
    path: Element,
    mode: HtmlSelectElement,
    k: HtmlSelectElement,
    token_box: HtmlElement,
    token_input: HtmlInputElement,
    token_entered: Rc<RefCell<Option<String>>>,
    _on_token: Closure<dyn FnMut(web_sys::Event)>,
    /// The controls' changes wake the frame loop.
    _on_change: Vec<Closure<dyn FnMut()>>,
}

fn element<T: JsCast>(document: &Document, id: &str) -> Result<T, String> {
    document
        .get_element_by_id(id)
        .ok_or_else(|| format!("the page has no #{id}"))?
        .dyn_into::<T>()
        .map_err(|_| format!("#{id} is not the element the viewer expects"))
}

impl Page {
    pub fn find(document: &Document, wake: &Wake) -> Result<Self, String> {
        let token_box: HtmlElement = element(document, "texel-token-box")?;
        let token_input: HtmlInputElement = element(document, "texel-token")?;
        let token_entered = Rc::new(RefCell::new(None));
        let on_token = {
            let entered = Rc::clone(&token_entered);
            let input = token_input.clone();
            let wake = wake.clone();
            Closure::<dyn FnMut(web_sys::Event)>::new(move |e: web_sys::Event| {
                e.prevent_default();
                *entered.borrow_mut() = Some(input.value());
                wake.wake();
            })
        };
        token_box
            .add_event_listener_with_callback("submit", on_token.as_ref().unchecked_ref())
            .map_err(|e| format!("{e:?}"))?;
        let mode: HtmlSelectElement = element(document, "texel-mode")?;
        let k: HtmlSelectElement = element(document, "texel-k")?;
        let on_change = vec![
            wake_on(&mode, "change", wake)?,
            wake_on(&k, "change", wake)?,
        ];
        Ok(Self {
            document: document.clone(),
            status: element(document, "texel-status")?,
            path: element(document, "texel-path")?,
            mode,
            k,
            token_box,
            token_input,
            token_entered,
            _on_token: on_token,
            _on_change: on_change,
        })
    }

    /// The mode chosen; a mode the browser does not draw yet reads as blended.
    pub fn mode(&self) -> Mode {
        match self.mode.value().parse::<DisplayMode>() {
            Ok(DisplayMode::Scans(m)) => m,
            _ => Mode::Blended,
        }
    }

    pub fn set_mode(&self, mode: Mode) {
        self.mode.set_value(mode.name());
    }

    pub fn k(&self) -> Option<u32> {
        self.k.value().parse().ok()
    }

    pub fn set_k(&self, k: u32) {
        self.k.set_value(&k.to_string());
    }

    pub fn show_status(&self, text: &str) {
        self.status.set_text_content(Some(text));
    }

    pub fn show_path(&self, text: &str) {
        self.path.set_text_content(Some(text));
    }

    /// Shows or hides the token box.
    pub fn ask_token(&self, ask: bool) {
        let hidden = self.token_box.hidden();
        if hidden == ask {
            self.token_box.set_hidden(!ask);
            if ask {
                let _ = self.token_input.focus();
            }
        }
    }

    /// A token the user entered since the last call.
    pub fn take_token(&self) -> Option<String> {
        self.token_entered.borrow_mut().take()
    }

    /// Sets `data-texel-<key>` on the body: what watchers read.
    pub fn set_data(&self, key: &str, value: &str) {
        if let Some(body) = self.document.body() {
            let _ = body.set_attribute(&format!("data-texel-{key}"), value);
        }
    }

    pub fn remove_data(&self, key: &str) {
        if let Some(body) = self.document.body() {
            let _ = body.remove_attribute(&format!("data-texel-{key}"));
        }
    }

    /// Replaces the address bar's query with `query` (no history entry).
    pub fn set_query(&self, query: &str) {
        if let Some(window) = web_sys::window()
            && let Ok(history) = window.history()
        {
            let _ = history.replace_state_with_url(&JsValue::NULL, "", Some(query));
        }
    }
}

/// Says on the page (and the console) why the viewer cannot go on.
pub fn fatal(message: &str) {
    web_sys::console::error_1(&JsValue::from_str(message));
    let Some(document) = web_sys::window().and_then(|w| w.document()) else {
        return;
    };
    if let Some(status) = document.get_element_by_id("texel-status") {
        status.set_text_content(Some(message));
        let _ = status.set_attribute("class", "error");
    }
    if let Some(body) = document.body() {
        let _ = body.set_attribute("data-texel-error", message);
    }
}

/// The page's clock in milliseconds (`performance.now()`).
pub fn now_ms() -> f64 {
    web_sys::window()
        .and_then(|w| w.performance())
        .map_or(0.0, |p| p.now())
}

/// The session's stored token, if the user gave one before (kept for the tab only).
pub fn stored_token() -> String {
    web_sys::window()
        .and_then(|w| w.session_storage().ok().flatten())
        .and_then(|s| s.get_item("texel-token").ok().flatten())
        .unwrap_or_default()
}

pub fn store_token(token: &str) {
    if let Some(s) = web_sys::window().and_then(|w| w.session_storage().ok().flatten()) {
        let _ = s.set_item("texel-token", token);
    }
}
