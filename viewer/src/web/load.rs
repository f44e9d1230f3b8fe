//! Where a page load's time goes: the page's clock (`performance.now()`, 0 at
//! navigation) at each step from the wasm's start to the ready signal, and the time
//! the frame loop spent decoding, uploading and drawing on the way. Published as JSON
//! in `data-texel-load` on `<body>`, which `texel-bench web` reads.

/// The steps of one load, ms after navigation (`None`: not reached yet).
#[derive(Debug, Default, Clone)]
pub struct LoadMarks {
    /// The wasm instantiated and its start function running.
    pub wasm: Option<f64>,
    /// The GPU adapter and device.
    pub gpu: Option<f64>,
    /// The renderer and its pipelines created.
    pub pipelines: Option<f64>,
    /// The WebSocket open.
    pub socket: Option<f64>,
    /// The daemon's snapshot (every listing) received.
    pub snapshot: Option<f64>,
    /// The last bytes of the scans the view needs received.
    pub fetched: Option<f64>,
    /// Every scan of the view uploaded.
    pub resident: Option<f64>,
    /// The first frame drawn (whatever it showed).
    pub first_frame: Option<f64>,
    /// The frame with the whole model drawn, at full quality.
    pub ready: Option<f64>,
    /// Frame-loop time until ready: decoding and applying messages, residency steps
    /// (uploads), and recording and submitting frames.
    pub pump_ms: f64,
    pub upload_ms: f64,
    pub draw_ms: f64,
    /// Frames drawn until ready.
    pub frames: u32,
}

impl LoadMarks {
    /// Sets a step's time the first time it is reached.
    pub fn mark(step: &mut Option<f64>, now_ms: f64) {
        if step.is_none() {
            *step = Some(now_ms);
        }
    }

    /// Whether the load is over (time is no longer added).
    pub fn done(&self) -> bool {
        self.ready.is_some()
    }

    /// The marks as a JSON object (absent steps as `null`).
    pub fn to_json(&self) -> String {
        let t = |v: Option<f64>| v.map_or_else(|| "null".to_string(), |v| format!("{v:.1}"));
        format!(
            "{{\"wasm\":{},\"gpu\":{},\"pipelines\":{},\"socket\":{},\"snapshot\":{},\
             \"fetched\":{},\"resident\":{},\"firstFrame\":{},\"ready\":{},\
             \"pumpMs\":{:.1},\"uploadMs\":{:.1},\"drawMs\":{:.1},\"frames\":{}}}",
            t(self.wasm),
            t(self.gpu),
            t(self.pipelines),
            t(self.socket),
            t(self.snapshot),
            t(self.fetched),
            t(self.resident),
            t(self.first_frame),
            t(self.ready),
            self.pump_ms,
            self.upload_ms,
            self.draw_ms,
            self.frames
        )
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn marks_are_kept_from_their_first_time_and_read_as_json() {
        let mut marks = LoadMarks::default();
        LoadMarks::mark(&mut marks.gpu, 12.34);
        LoadMarks::mark(&mut marks.gpu, 99.0);
        marks.frames = 3;
        let json: serde_json::Value = serde_json::from_str(&marks.to_json()).unwrap();
        assert_eq!(json["gpu"].as_f64(), Some(12.3));
        assert!(json["ready"].is_null());
        assert_eq!(json["frames"].as_u64(), Some(3));
        assert!(!marks.done());
    }
}
