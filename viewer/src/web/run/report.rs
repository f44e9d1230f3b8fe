//! The page's report after each frame: the load's steps (`data-texel-load`), the
//! ready signal once the model asked for is on screen, the status line and figures a
//! few times a second, and the address bar kept as the view's deep link.

use super::super::load::LoadMarks;
use super::super::page::now_ms;
use super::super::view_query;
use super::{READY_AFTER_FRAMES, Web};

impl Web {
    /// The status line a few times a second, the deep link of the view, and the
    /// ready signal once the model asked for is on screen.
    pub(super) fn report(&mut self, now: f64, drew: bool) {
        let v = &self.viewer;
        let settled = v.residency_stats.in_flight == 0 && v.residency_stats.pending == 0;
        let complete = v.snapshot_complete && settled && !v.model.is_empty();
        // Only a frame drawn with the whole model counts.
        self.complete_frames = match (complete, drew) {
            (true, true) => self.complete_frames.saturating_add(1),
            (true, false) => self.complete_frames,
            (false, _) => 0,
        };
        self.mark_load(now, drew);
        let v = &self.viewer;
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
            let scans = v.model.len();
            self.ready_connection = Some(connection);
            // After the frame's submission, not at its start.
            let at = now_ms();
            if !self.load.done() {
                self.load.ready = Some(at);
                self.load.frames = u32::try_from(self.frames_drawn).unwrap_or(u32::MAX);
                self.page.set_data("load", &self.load.to_json());
            }
            // The figures a watcher reads with the signal are this frame's (an idle
            // page may not refresh them soon).
            self.show_status(now);
            self.page.set_data("ready-ms", &format!("{at:.0}"));
            self.page.set_data("ready", &scans.to_string());
            self.page
                .set_data("ready-connection", &connection.to_string());
        }
        if now - self.last_status_ms >= 250.0 {
            self.show_status(now);
        }
    }

    /// The status line, the figures in `data-texel-*` and the deep link of the view.
    fn show_status(&mut self, now: f64) {
        self.last_status_ms = now;
        let v = &self.viewer;
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
        if !self.load.done() {
            self.page.set_data("load", &self.load.to_json());
        }
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

    /// The load's steps reached by this frame (the first load only: a reconnection's
    /// model is signalled by `data-texel-ready-connection`).
    fn mark_load(&mut self, now: f64, drew: bool) {
        if self.load.done() {
            return;
        }
        let v = &self.viewer;
        let load = &mut self.load;
        if let Some(opened) = self.link.opened_ms {
            LoadMarks::mark(&mut load.socket, opened);
        }
        if v.snapshot_complete {
            LoadMarks::mark(&mut load.snapshot, now);
            if v.residency_stats.in_flight == 0 && !v.model.is_empty() {
                // The bytes of the last scan came before this frame decoded them.
                LoadMarks::mark(&mut load.fetched, self.link.last_chunk_ms.min(now));
                if v.residency_stats.pending == 0 {
                    LoadMarks::mark(&mut load.resident, now_ms());
                }
            }
        }
        if drew {
            LoadMarks::mark(&mut load.first_frame, now_ms());
        }
    }
}
