//! Popping figures for a fly-through: how much the image changes from one frame to
//! the next, largest at the frames where the drawn tiles switched (or a cross-fade
//! was under way), against the same frames drawn at full detail (camera motion
//! alone); and the change a switch alone makes, the camera held still (the previous
//! frame's tiles and this frame's drawn from this frame's camera).

/// The mean absolute RGB difference of two images of the same size, in 8-bit steps
/// (0 to 255); `None` when the sizes differ or the images are empty.
pub fn frame_change(a: &image::RgbaImage, b: &image::RgbaImage) -> Option<f64> {
    if a.dimensions() != b.dimensions() || a.width() == 0 || a.height() == 0 {
        return None;
    }
    let sum: u64 = a
        .pixels()
        .zip(b.pixels())
        .map(|(p, q)| (0..3).map(|k| u64::from(p[k].abs_diff(q[k]))).sum::<u64>())
        .sum();
    Some(sum as f64 / (3.0 * f64::from(a.width()) * f64::from(a.height())))
}

/// The figures of one fly-through.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PopMeasure {
    /// Frame-to-frame changes measured.
    pub changes: usize,
    /// Of those, at switch frames.
    pub switch_frames: usize,
    /// Largest change at a switch frame (mean absolute RGB difference, 8-bit steps).
    pub max_switch_change: f64,
    /// Largest change at any frame.
    pub max_change: f64,
    /// Mean change over all frames.
    pub mean_change: f64,
}

/// The figures of a fly-through's `frames`; `switched[i]` marks frame `i` (its change
/// from frame `i - 1`) as a switch frame. Pass one fly-through's marks with another's
/// frames (e.g. at full detail) to measure the same frames without switches.
pub fn popping_measure(frames: &[image::RgbaImage], switched: &[bool]) -> PopMeasure {
    let mut out = PopMeasure::default();
    let mut total = 0.0;
    for i in 1..frames.len() {
        let Some(change) = frame_change(&frames[i - 1], &frames[i]) else {
            continue;
        };
        out.changes += 1;
        total += change;
        out.max_change = out.max_change.max(change);
        if switched.get(i).copied().unwrap_or(false) {
            out.switch_frames += 1;
            out.max_switch_change = out.max_switch_change.max(change);
        }
    }
    if out.changes > 0 {
        out.mean_change = total / out.changes as f64;
    }
    out
}

/// The largest excess, over the switch frames, of a fly-through's frame-to-frame
/// change over the same frames' change in `reference` (the fly-through at full
/// detail): the part of the change that camera motion does not explain. 0 without
/// switch frames.
pub fn popping_excess(
    frames: &[image::RgbaImage],
    reference: &[image::RgbaImage],
    switched: &[bool],
) -> f64 {
    let mut worst = 0.0f64;
    for i in 1..frames.len().min(reference.len()) {
        if !switched.get(i).copied().unwrap_or(false) {
            continue;
        }
        if let (Some(a), Some(b)) = (
            frame_change(&frames[i - 1], &frames[i]),
            frame_change(&reference[i - 1], &reference[i]),
        ) {
            worst = worst.max(a - b);
        }
    }
    worst
}

/// The change switches alone make: per frame, this frame's image against the previous
/// frame's tiles drawn from this frame's camera.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SwitchMeasure {
    pub frames: usize,
    /// Frames where the image changed at all.
    pub changed_frames: usize,
    /// Largest change (mean absolute RGB difference, 8-bit steps).
    pub max_change: f64,
    pub mean_change: f64,
}

/// [`SwitchMeasure`] of `(before, after)` pairs: the previous frame's tiles and this
/// frame's, both from this frame's camera.
pub fn switch_measure(pairs: &[(image::RgbaImage, image::RgbaImage)]) -> SwitchMeasure {
    let mut out = SwitchMeasure::default();
    let mut total = 0.0;
    for (before, after) in pairs {
        let Some(change) = frame_change(before, after) else {
            continue;
        };
        out.frames += 1;
        total += change;
        out.changed_frames += usize::from(change > 0.0);
        out.max_change = out.max_change.max(change);
    }
    if out.frames > 0 {
        out.mean_change = total / out.frames as f64;
    }
    out
}
