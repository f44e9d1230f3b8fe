//! The window's refinement steps: a step of the full-quality frame under way changes
//! nothing on screen, so it is taken without drawing the window (no swapchain image,
//! no overlay), the steps follow each other closely, and input is read between them.

use web_time::Instant;

use super::App;
use crate::adaptive::{Decision, Quality, Refinement};

/// What [`App::refine_without_drawing`] did.
pub(super) enum RefineStep {
    /// A step was taken and waited for; more follow. Nothing to draw.
    Pending,
    /// The last step was taken: draw the window (the pacer now idles, so it shows
    /// the full picture). `began`: when the frame's first step was.
    Done { began: Option<Instant> },
    /// No refinement to step here (none under way, the view changed, input waits, or
    /// tiles or VDTM are drawn): redraw as usual.
    NotHere,
}

impl App {
    pub(super) fn refine_without_drawing(&mut self, now: Instant) -> anyhow::Result<RefineStep> {
        let Some(w) = self.window.as_mut() else {
            return Ok(RefineStep::NotHere);
        };
        let (width, height) = (w.config.width, w.config.height);
        let scans_only = w.vdtm.is_none() && !(w.tiles.is_some() && self.viewer.show_tiles);
        if !(w.adaptive.refining() && scans_only && !self.pacing.dirty) {
            return Ok(RefineStep::NotHere);
        }
        let Some(camera) = self.viewer.camera(width, height) else {
            return Ok(RefineStep::NotHere);
        };
        let key = (
            camera,
            self.viewer.settings.clone(),
            self.viewer.model.events_applied(),
        );
        if self.pacing.view_changed(&key)
            || self.pacing.pacer.decide(false, now) != Decision::Draw(Quality::Full)
        {
            return Ok(RefineStep::NotHere);
        }
        match w
            .adaptive
            .refine(&mut w.renderer, &camera, &self.viewer.settings)?
        {
            Refinement::Pending { .. } => {
                w.gpu.wait_idle()?;
                Ok(RefineStep::Pending)
            }
            Refinement::Done(stats) => {
                self.viewer.stats = stats;
                self.viewer.refining = None;
                self.pacing.drawn(Quality::Full, key);
                Ok(RefineStep::Done {
                    began: self.pacing.refine_started.take(),
                })
            }
        }
    }
}
