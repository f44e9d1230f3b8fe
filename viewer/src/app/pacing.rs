//! When the window draws: only when something changed (input, the model, the
//! overlay, a refinement still to come), so an idle window submits nothing to the GPU;
//! and the report of `--exit-when-idle`, which counts what it submitted while idle.

// `web_time`: the std clock natively, the browser's in wasm (where std's panics).
use web_time::{Duration, Instant};

use crate::adaptive::{FramePacer, Quality};
use crate::camera::VirtualCamera;
use crate::gpu::RenderSettings;

/// How often a waiting window looks at its source for new events (no frame is drawn
/// unless one came).
pub(super) const SOURCE_POLL: Duration = Duration::from_millis(50);

/// How soon a residency step still under way (uploads paced over frames) is taken.
const STEP_AGAIN: Duration = Duration::from_millis(30);

/// What a scene frame depends on: the camera, the settings and the model's state.
pub(super) type ViewKey = (VirtualCamera, RenderSettings, u64);

pub(super) struct Pacing {
    pub pacer: FramePacer,
    /// The view the last scene frame showed.
    last_key: Option<ViewKey>,
    /// Input, an event or the overlay asks for a redraw.
    pub dirty: bool,
    /// The overlay asked to be drawn again at this instant.
    pub overlay_at: Option<Instant>,
    /// The last scene frame's time (redraw start to GPU done), ms.
    pub last_frame_ms: f64,
    /// When the full-quality frame under way took its first step.
    pub refine_started: Option<Instant>,
    exit_when_idle: Option<Duration>,
    /// When the window first had nothing to do, the GPU submissions then and the
    /// scene frames drawn then.
    idle_since: Option<(Instant, u64, u64)>,
    frames: u64,
}

impl Pacing {
    pub fn new(adaptive: bool, exit_when_idle: Option<Duration>) -> Self {
        Self {
            pacer: FramePacer::new(adaptive),
            last_key: None,
            dirty: true,
            overlay_at: None,
            last_frame_ms: 0.0,
            refine_started: None,
            exit_when_idle,
            idle_since: None,
            frames: 0,
        }
    }

    pub fn view_changed(&self, key: &ViewKey) -> bool {
        self.last_key.as_ref().is_some_and(|last| last != key)
    }

    /// A scene frame of `quality` showing `key` was drawn.
    pub fn drawn(&mut self, quality: Quality, key: ViewKey) {
        self.pacer.drawn(quality);
        self.last_key = Some(key);
        self.frames += 1;
    }

    /// When the next redraw is wanted: now (input, a camera flying, something that
    /// changes by itself), at a deadline (the settle time before the full frame, the
    /// overlay's repaint, a residency step), or never (`None`: idle).
    pub fn next_redraw(&self, now: Instant, busy: bool, stepping: bool) -> Option<Instant> {
        if self.dirty || busy {
            return Some(now);
        }
        [
            self.pacer.wake_at(now),
            self.overlay_at,
            stepping.then_some(now + STEP_AGAIN),
        ]
        .into_iter()
        .flatten()
        .min()
    }

    /// With `--exit-when-idle D`: once the window first has nothing to do, counts the
    /// GPU submissions and scene frames of the next `D` (whatever happens in them, so
    /// a window that keeps drawing is caught) and returns the line to print.
    pub fn idle_report(&mut self, now: Instant, idle: bool) -> Option<String> {
        let wait = self.exit_when_idle?;
        let submissions = crate::gpu::submissions();
        let (since, at_start, frames_then) = match self.idle_since {
            Some(s) => s,
            None if idle => {
                self.idle_since = Some((now, submissions, self.frames));
                return None;
            }
            None => return None,
        };
        if now.duration_since(since) < wait {
            return None;
        }
        Some(format!(
            "idle {:.1} s: {} GPU submissions, {} frames drawn",
            now.duration_since(since).as_secs_f64(),
            submissions - at_start,
            self.frames - frames_then
        ))
    }
}
