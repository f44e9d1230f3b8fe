//! The egui overlay: mode, blending, stretched triangles, frame statistics, the scan
//! list with visibility toggles and jumps to acquisition views.

use super::ViewerState;
use crate::composite::{MAX_K, Mode};
use crate::gpu::Strategy;

/// `roomy`: the window is wide enough to show the panel open at first (in a small
/// window it starts folded, so the model stays visible).
pub(super) fn panel(ctx: &egui::Context, v: &mut ViewerState, roomy: bool) {
    egui::Window::new("texel")
        .default_width(240.0)
        .default_pos([8.0, 8.0])
        .default_open(roomy)
        .show(ctx, |ui| {
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
            ui.separator();
            egui::ComboBox::from_label("mode")
                .selected_text(v.settings.composite.mode.name())
                .show_ui(ui, |ui| {
                    for m in Mode::ALL {
                        ui.selectable_value(&mut v.settings.composite.mode, m, m.name());
                    }
                });
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
