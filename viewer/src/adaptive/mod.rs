//! Adaptive quality and frame pacing, independent of any window: the controller that
//! sizes the interactive frame to a frame-time budget, the pacer that decides when a
//! frame is drawn at all (and at which quality), and the GPU side that renders the
//! cheap frame, the full-quality frame and shows either (`present.rs`). The window
//! and `texel-bench viewer --adaptive` share all of it.

mod present;

// `web_time`: the std clock natively, the browser's in wasm (where std's panics).
use web_time::{Duration, Instant};

pub use present::{AdaptiveRenderer, Refinement, Shown};

use crate::composite::Mode;
use crate::gpu::RenderSettings;

/// The interactive frame's default budget, milliseconds (15 frames/s).
pub const DEFAULT_INTERACTIVE_MS: f64 = 66.0;

/// The share of the budget the controller aims at: frame times on a shared machine
/// spread about 1.3x from median to 95th percentile, so aiming at the budget itself
/// would keep only half the frames within it.
pub const BUDGET_HEADROOM: f64 = 0.75;

/// How long the view must stay unchanged before the full-quality frame is drawn.
pub const DEFAULT_SETTLE: Duration = Duration::from_millis(150);

/// Drives the interactive frame's resolution scale (a fraction of the window's width
/// and height) so that the measured frame time meets a budget: it aims at
/// [`BUDGET_HEADROOM`] of it (the target).
///
/// A frame costs about `a + b s²` (a fixed part, and the pixels). The update
/// `s² ← s² (target / t)^gain` has the target as its fixed point; with `0 < gain ≤ 1`
/// its slope there is `1 − gain · b s² / target`, within `(1 − gain, 1)`, so it
/// converges without overshoot whatever `a` and `b` are. Measurements are smoothed
/// (a median of the last three) so one slow frame on a shared machine does not halve
/// the picture.
#[derive(Debug, Clone)]
pub struct ScaleController {
    budget_ms: f64,
    scale: f64,
    pub min_scale: f64,
    pub max_scale: f64,
    pub gain: f64,
    recent: [f64; 3],
    seen: usize,
}

impl ScaleController {
    /// A controller for `budget_ms` (floored at 1 ms; a non-finite budget counts as
    /// the default), starting at half resolution.
    pub fn new(budget_ms: f64) -> Self {
        let budget_ms = if budget_ms.is_finite() {
            budget_ms.max(1.0)
        } else {
            DEFAULT_INTERACTIVE_MS
        };
        Self {
            budget_ms,
            scale: 0.5,
            min_scale: 0.125,
            max_scale: 1.0,
            gain: 0.7,
            recent: [0.0; 3],
            seen: 0,
        }
    }

    pub fn budget_ms(&self) -> f64 {
        self.budget_ms
    }

    /// The frame time aimed at: [`BUDGET_HEADROOM`] of the budget.
    pub fn target_ms(&self) -> f64 {
        self.budget_ms * BUDGET_HEADROOM
    }

    /// The scale the next interactive frame is drawn at.
    pub fn scale(&self) -> f64 {
        self.scale
    }

    /// Takes the time the last interactive frame took (at [`Self::scale`]) and returns
    /// the next scale. A non-finite or negative time is ignored.
    pub fn observe(&mut self, frame_ms: f64) -> f64 {
        if !(frame_ms.is_finite() && frame_ms >= 0.0) {
            return self.scale;
        }
        self.recent[self.seen % 3] = frame_ms;
        self.seen += 1;
        let t = if self.seen >= 3 {
            let mut r = self.recent;
            r.sort_by(f64::total_cmp);
            r[1]
        } else {
            frame_ms
        };
        // A frame measured as (nearly) free: grow by the largest step allowed.
        let ratio = (self.target_ms() / t.max(1e-3)).clamp(0.25, 4.0);
        let pixels = self.scale * self.scale * ratio.powf(self.gain);
        self.scale = pixels
            .sqrt()
            .clamp(self.min_scale.min(self.max_scale), self.max_scale);
        self.scale
    }
}

/// The size of a frame drawn at `scale` of `width` x `height`: at least 1 x 1.
pub fn scaled_size(width: u32, height: u32, scale: f64) -> (u32, u32) {
    let s = if scale.is_finite() {
        scale.clamp(0.0, 1.0)
    } else {
        1.0
    };
    let dim = |d: u32| ((f64::from(d) * s).round() as u32).clamp(1, d.max(1));
    (dim(width), dim(height))
}

/// The settings of the interactive frame: each scan's coarse triangles, and the cheap
/// mode chosen (`cheap`) with `k = 1` for the composite modes. Modes that are not a composite of the scans
/// (scan colour, reliability) keep theirs: what they show is the point.
pub fn interactive_settings(full: &RenderSettings, cheap: Mode) -> RenderSettings {
    let mut s = full.clone();
    s.coarse = true;
    match full.composite.mode {
        Mode::Blended | Mode::Best | Mode::Painter => {
            s.composite.mode = cheap;
            s.composite.k = 1;
        }
        _ => s.composite.k = 1,
    }
    s
}

/// Which quality a frame is drawn at.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Quality {
    /// Reduced resolution, cheap mode, upscaled.
    Interactive,
    /// The settings asked for, at full resolution.
    Full,
}

/// What the window should do now.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Decision {
    /// Draw the scene at this quality.
    Draw(Quality),
    /// Nothing changed since the full-quality frame: draw nothing.
    Idle,
    /// The view just stopped: wake at this instant to draw the full-quality frame.
    WaitUntil(Instant),
}

/// Decides, from whether the view (camera, model, settings, size) changed since the
/// last frame drawn, whether to draw and at which quality: interactive frames while it
/// changes, the full-quality frame once it has been still for `settle`, then nothing
/// until it changes again. With `adaptive` off every change is drawn at full quality.
#[derive(Debug, Clone)]
pub struct FramePacer {
    pub settle: Duration,
    pub adaptive: bool,
    last_change: Option<Instant>,
    full_shown: bool,
}

impl FramePacer {
    pub fn new(adaptive: bool) -> Self {
        Self {
            settle: DEFAULT_SETTLE,
            adaptive,
            last_change: None,
            full_shown: false,
        }
    }

    /// `changed`: the view differs from the one last drawn.
    pub fn decide(&mut self, changed: bool, now: Instant) -> Decision {
        if changed {
            self.last_change = Some(now);
            self.full_shown = false;
            return Decision::Draw(if self.adaptive {
                Quality::Interactive
            } else {
                Quality::Full
            });
        }
        if self.full_shown {
            return Decision::Idle;
        }
        match self.last_change {
            Some(t) if now.duration_since(t) < self.settle => Decision::WaitUntil(t + self.settle),
            _ => Decision::Draw(Quality::Full),
        }
    }

    /// A frame of `quality` is on screen.
    pub fn drawn(&mut self, quality: Quality) {
        if quality == Quality::Full {
            self.full_shown = true;
        }
    }

    /// When a frame is due without anything changing: the full-quality frame at the
    /// end of the settle time (now, if nothing was drawn yet); `None` once it is shown.
    pub fn wake_at(&self, now: Instant) -> Option<Instant> {
        if self.full_shown {
            return None;
        }
        Some(self.last_change.map_or(now, |t| t + self.settle))
    }

    /// Whether the full-quality frame is on screen.
    pub fn settled(&self) -> bool {
        self.full_shown
    }
}

#[cfg(test)]
mod tests;
