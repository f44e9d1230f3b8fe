//! The egui overlay: the connection, the daemon's status and the stream latency;
//! mode, blending, stretched triangles, frame statistics, the scan list with
//! visibility toggles and jumps to acquisition views.

use super::ViewerState;
use crate::composite::{MAX_K, Mode};
use crate::gpu::Strategy;
use crate::live::ConnectionState;
use crate::tonemap::{ToneMapSettings, ToneOperator};

/// `roomy`: the window is wide enough to show the panel open at first (in a small
/// window it starts folded, so the model stays visible).
pub(super) fn panel(ctx: &egui::Context, v: &mut ViewerState, roomy: bool) {
    quality_badge(ctx, v);
    egui::Window::new("texel")
        .default_width(240.0)
        .default_pos([8.0, 8.0])
        .default_open(roomy)
        .show(ctx, |ui| {
            source_section(ui, v);
            ui.separator();
            ui.label(format!("{:.1} frames/s", v.fps));
            ui.label(format!(
                "scans {}: drawn {}, outside view {}, facing away {}, hidden {}",
                v.stats.scans,
                v.stats.drawn,
                v.stats.culled_frustum,
                v.stats.culled_facing,
                v.stats.hidden
            ));
            ui.label(format!(
                "targets {:.1} MiB, scans {:.1} MiB",
                v.stats.target_memory.total() as f64 / 1048576.0,
                v.stats.scan_bytes as f64 / 1048576.0
            ));
            residency_section(ui, v);
            if let Some(status) = &v.vdtm_status {
                ui.label(status.describe());
                if let Some(s) = v.vdtm_settings.as_mut() {
                    ui.checkbox(&mut s.resolution_term, "VDTM resolution term");
                    let mut feather = s.feather_px > 0.0;
                    ui.checkbox(&mut feather, "VDTM feathering at image borders");
                    s.feather_px = if feather {
                        crate::vdtm::VdtmSettings::FEATHER_PX
                    } else {
                        0.0
                    };
                }
            }
            if let Some(t) = &v.tile_stats {
                ui.checkbox(&mut v.show_tiles, "level-of-detail tiles (L)");
                if v.show_tiles {
                    ui.label(format!(
                        "tiles: {} drawn, {} triangles, {} resident ({:.1} MiB), {} wanted, {} loading",
                        t.tiles_drawn,
                        t.triangles_drawn,
                        t.resident_tiles,
                        t.resident_bytes as f64 / 1048576.0,
                        t.tiles_wanted,
                        t.loads_in_flight
                    ));
                    ui.checkbox(&mut v.scans_below_tiles, "scans below the finest tiles");
                    if v.scans_below_tiles {
                        ui.label(format!(
                            "{} finest tiles show their scans ({} drawn)",
                            t.tiles_with_scans, v.stats.drawn
                        ));
                    }
                }
            }
            ui.separator();
            egui::ComboBox::from_label("mode")
                .selected_text(v.settings.composite.mode.name())
                .show_ui(ui, |ui| {
                    for m in Mode::ALL {
                        ui.selectable_value(&mut v.settings.composite.mode, m, m.name());
                    }
                });
            ui.checkbox(
                &mut v.settings.points,
                "points: the scans as a point proxy (Lechelek et al. 2019)",
            );
            if v.settings.points {
                tone_map_controls(ui, &mut v.settings.tone_map);
            }
            ui.add(
                egui::Slider::new(&mut v.settings.composite.blend_threshold, 0.0..=1.0)
                    .text("blend threshold"),
            );
            ui.add(egui::Slider::new(&mut v.settings.composite.k, 1..=MAX_K).text("k"));
            ui.add(egui::Slider::new(&mut v.settings.range_gamma, 0.25..=4.0).text("range gamma"));
            ui.checkbox(&mut v.settings.keep_stretched, "keep stretched triangles");
            let mut naive = v.settings.strategy == Strategy::NaiveLayers;
            if ui.checkbox(&mut naive, "naive layers (baseline)").changed() {
                v.settings.strategy = if naive {
                    Strategy::NaiveLayers
                } else {
                    Strategy::default()
                };
            }
            ui.add(egui::Slider::new(&mut v.fov_deg, 10.0..=120.0).text("field of view"));
            ui.checkbox(&mut v.follow_newest, "follow the newest scan");
            ui.label("drag: orbit, right-drag: pan, wheel: zoom, WASD QE: fly");
            ui.separator();
            egui::ScrollArea::vertical()
                .max_height(240.0)
                .show(ui, |ui| {
                    let ids: Vec<u64> = v.model.scans().iter().map(|s| s.id).collect();
                    for id in ids {
                        ui.horizontal(|ui| {
                            let mut shown = !v.settings.hidden.contains(&id);
                            if ui.checkbox(&mut shown, format!("scan {id}")).changed() {
                                if shown {
                                    v.settings.hidden.remove(&id);
                                } else {
                                    v.settings.hidden.insert(id);
                                }
                            }
                            if ui.button("view").clicked() {
                                v.jump_to = Some(id);
                            }
                        });
                    }
                });
        });
}

/// Which quality is on screen, in the bottom-right corner: the interactive frame
/// (its resolution and mode) while the view moves, then the full-quality one.
fn quality_badge(ctx: &egui::Context, v: &ViewerState) {
    let Some((shown, ms)) = v.quality else {
        return;
    };
    let colour = match shown.quality {
        crate::adaptive::Quality::Interactive => egui::Color32::from_rgb(230, 170, 80),
        crate::adaptive::Quality::Full => egui::Color32::from_rgb(90, 200, 90),
    };
    egui::Area::new(egui::Id::unique("quality"))
        .anchor(egui::Align2::RIGHT_BOTTOM, [-8.0, -8.0])
        .interactable(false)
        .show(ctx, |ui| {
            egui::Frame::popup(ui.style()).show(ui, |ui| {
                let refining = match v.refining {
                    // Later steps do not draw the window: the count of all is what holds.
                    Some((_, steps)) => format!(", refining in {steps} steps"),
                    None => String::new(),
                };
                ui.colored_label(
                    colour,
                    format!("{} ({ms:.0} ms){refining}", shown.describe()),
                );
            });
        });
}

/// What of the model is on the GPU: resident / known scans, budget used, fetches in
/// flight, and what the view needs but the budget left out.
fn residency_section(ui: &mut egui::Ui, v: &ViewerState) {
    let r = &v.residency_stats;
    let mib = |b: u64| b as f64 / 1048576.0;
    ui.label(format!(
        "resident {}/{} scans, GPU {:.1}/{:.0} MiB, fetching {}{}",
        r.resident,
        r.known,
        mib(r.used_bytes),
        mib(r.budget_bytes),
        r.in_flight,
        if r.pending > r.in_flight {
            format!(" ({} waiting)", r.pending - r.in_flight)
        } else {
            String::new()
        }
    ));
    if r.left_out > 0 {
        ui.colored_label(
            egui::Color32::from_rgb(230, 170, 80),
            format!(
                "over budget: the view needs {} scans, {} left out (the most reliable are shown)",
                r.needed, r.left_out
            ),
        );
    }
    let unavailable = v.residency.unavailable_scans().len();
    if unavailable > 0 {
        ui.label(format!("{unavailable} scans unavailable"));
    }
}

/// The model's source: connection state, the daemon's status (sources, counters,
/// stage latencies) and the stream latency.
fn source_section(ui: &mut egui::Ui, v: &ViewerState) {
    if let Some(state) = &v.connection {
        let colour = match state {
            ConnectionState::Connected { .. } => egui::Color32::from_rgb(90, 200, 90),
            ConnectionState::Connecting { .. } => egui::Color32::from_rgb(220, 200, 80),
            ConnectionState::Retrying { .. } | ConnectionState::Ended { .. } => {
                egui::Color32::from_rgb(230, 110, 90)
            }
        };
        ui.colored_label(colour, state.describe());
    }
    ui.label(format!(
        "model: {} scans{}",
        v.model.len(),
        if v.snapshot_complete {
            ""
        } else {
            " (snapshot arriving)"
        }
    ));
    if let Some((p50, max)) = v.latency.summary() {
        ui.label(format!(
            "stream latency (received -> drawn): p50 {p50:.0} ms, max {max:.0} ms"
        ));
    }
    let Some((status, at)) = &v.status else {
        return;
    };
    ui.label(format!(
        "daemon up {:.0} s, {} viewers (status {:.1} s old)",
        status.uptime_s,
        status.clients,
        at.elapsed().as_secs_f64()
    ));
    if let Some(e2e) = status.stages.iter().find(|s| s.stage == "end_to_end") {
        ui.label(format!(
            "daemon frame -> published: p50 {:.0} ms, p99 {:.0} ms",
            e2e.p50_ms, e2e.p99_ms
        ));
    }
    egui::CollapsingHeader::new("daemon status")
        .default_open(false)
        .show(ui, |ui| {
            for s in &status.sources {
                ui.label(format!(
                    "{} ({}): {}, range {:.1} fps, EO {:.1} fps{}",
                    s.name,
                    s.kind,
                    s.state,
                    s.range_fps,
                    s.eo_fps,
                    s.last_error
                        .as_ref()
                        .map_or(String::new(), |e| format!(", last error: {e}"))
                ));
            }
            for st in &status.stages {
                ui.label(format!(
                    "{}: p50 {:.1} ms, p99 {:.1} ms ({} samples)",
                    st.stage, st.p50_ms, st.p99_ms, st.samples
                ));
            }
            for q in &status.queues {
                ui.label(format!("queue {}: {}/{}", q.name, q.depth, q.capacity));
            }
            let nonzero: Vec<String> = status
                .counters
                .iter()
                .filter(|(_, n)| **n > 0)
                .map(|(k, n)| format!("{k} {n}"))
                .collect();
            if !nonzero.is_empty() {
                ui.label(nonzero.join(", "));
            }
            if let Some(r) = &status.recording {
                ui.label(format!(
                    "recording {}: {:.1} MiB, {} messages, {} errors",
                    r.path,
                    r.bytes as f64 / 1048576.0,
                    r.messages,
                    r.errors
                ));
            }
        });
}

/// HDR on or off and, when on, the tone-mapping controls (Lechelek et al. 2019 §6:
/// Reinhard's operator or a filmic curve, exposure, gamma, key, auto-exposure).
fn tone_map_controls(ui: &mut egui::Ui, tone_map: &mut Option<ToneMapSettings>) {
    let mut hdr = tone_map.is_some();
    if ui
        .checkbox(&mut hdr, "HDR: radiance from exposed frames, tone-mapped")
        .changed()
    {
        *tone_map = hdr.then(ToneMapSettings::default);
    }
    let Some(t) = tone_map.as_mut() else {
        return;
    };
    egui::ComboBox::from_label("tone operator")
        .selected_text(t.operator.name())
        .show_ui(ui, |ui| {
            for op in ToneOperator::ALL {
                ui.selectable_value(&mut t.operator, op, op.name());
            }
        });
    ui.add(egui::Slider::new(&mut t.exposure_ev, -8.0..=8.0).text("exposure (EV)"));
    ui.add(egui::Slider::new(&mut t.gamma, 1.0..=3.0).text("gamma"));
    ui.add(egui::Slider::new(&mut t.key, 0.02..=0.9).text("key"));
    let mut auto = t.adaptation.is_none();
    if ui
        .checkbox(&mut auto, "auto-exposure (log-average luminance)")
        .changed()
    {
        t.adaptation = if auto { None } else { Some(1.0) };
    }
    if let Some(level) = t.adaptation.as_mut() {
        ui.add(
            egui::Slider::new(level, 1.0e-4..=1.0e3)
                .logarithmic(true)
                .text("adaptation level"),
        );
    }
}
