//! The scans below the finest tiles (Liu 2014 §3: the tree's leaves are the scans
//! themselves): which finest tiles show their scans and how far the switch has faded
//! in ([`ScanRamp`]), and drawing a frame of them (which scans: `scan_choice.rs`).
//! The scans are drawn first with view-dependent blending; the tile pass then draws
//! over them, giving way on their surface (`tile.wgsl`), so a tile still fills
//! wherever the chosen scans did not reach: no hole. Every tile gives way where scans
//! drew, not only those that asked for them: the scans are drawn anyway and carry the
//! EO images' detail. Where the tiles still showed over ground whose scans were
//! asked for, the frame's depth is read back as demand for the next choice
//! ([`TileRenderer::feed_back_coverage`], `coverage.rs`).

use std::collections::{BTreeMap, BTreeSet};

use texel::model::{ModelScan, ScanId};
use texel_lod::{TileId, TileIndex};

use super::coverage::depth_samples;
use super::image_target::ImageTarget;
use super::pass::PassTarget;
use super::scan_choice::drawn_holding;
use super::source::TileSource;
use super::{TileError, TileFrameStats, TileRenderer};
use crate::camera::VirtualCamera;
use crate::gpu::{FrameStats, GpuError, RenderSettings, RenderTarget, Renderer, Strategy};

/// How the scans below the finest tiles are chosen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HybridSettings {
    /// Draw the scans below finest tiles the view still finds too coarse.
    pub enabled: bool,
    /// Scans drawn per such tile: more fill more of the tile with scan detail and
    /// cost a scan pass each.
    pub scans_per_tile: usize,
    /// Scans that count at each point of a tile's surface when choosing them: the
    /// most reliable this many, as blending would weigh them.
    pub scans_per_point: usize,
    /// A scan counts for a tile, or a point, when its bounds come this close, metres.
    pub margin_m: f64,
    /// Scans drawn per tile beyond `scans_per_tile` for the points where earlier
    /// frames still showed the tile (`coverage.rs`); 0 turns the feedback off.
    pub feedback_scans_per_tile: usize,
    /// The feedback reads every this many pixels across and down.
    pub feedback_stride_px: u32,
    /// One demand point per cell of this size, metres.
    pub feedback_cell_m: f64,
    /// The scan pass fills the holes the drawn scans enclose, and the tiles give way
    /// there ([`RenderSettings::fill_enclosed_holes`]).
    pub fill_scan_holes: bool,
}

impl HybridSettings {
    /// Feedback rounds that read every pixel once: each reads one pixel of every
    /// `feedback_stride_px`-square block, a different one each round
    /// ([`super::coverage::grid_offset`]).
    pub fn feedback_rounds_to_read_every_pixel(&self) -> usize {
        let stride = self.feedback_stride_px.max(1) as usize;
        stride * stride
    }
}

impl Default for HybridSettings {
    fn default() -> Self {
        Self {
            enabled: true,
            scans_per_tile: 8,
            scans_per_point: 4,
            margin_m: 0.5,
            feedback_scans_per_tile: 64,
            feedback_stride_px: 4,
            feedback_cell_m: 0.1,
            fill_scan_holes: true,
        }
    }
}

/// Per finest tile, how far its scans have faded in, moving towards 1 while the view
/// wants them and back to 0 after, over the fade time. Tiles give way to the scans
/// in the largest share's part of their pixels ([`Self::share`]): one share for the
/// frame, so a tile joining while scans already show starts where the others are
/// and nothing already shown fades back out.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ScanRamp {
    shares: BTreeMap<TileId, f32>,
    last_s: Option<f64>,
}

impl ScanRamp {
    /// Steps every share at time `now_s` towards 1 for the tiles in `wanted`, towards
    /// 0 for the others (dropped at 0). A fade time of 0 (or less) switches at once.
    pub fn update(&mut self, wanted: &BTreeSet<TileId>, now_s: f64, fade_s: f64) {
        let dt = match self.last_s {
            Some(last) if now_s.is_finite() && now_s > last => now_s - last,
            _ => 0.0,
        };
        if now_s.is_finite() {
            self.last_s = Some(now_s);
        }
        // Guard: no fade (or a bad one) is a step of the whole way.
        let step = if fade_s > 1e-9 && fade_s.is_finite() {
            (dt / fade_s) as f32
        } else {
            1.0
        };
        let joining_at = self.share();
        for id in wanted {
            self.shares.entry(*id).or_insert(joining_at);
        }
        self.shares.retain(|id, share| {
            if wanted.contains(id) {
                // A tile newly wanted starts its fade on the next frame with a share
                // above 0, so its scans are loaded and drawn from the first frame.
                *share = (*share + step.max(f32::EPSILON)).min(1.0);
                true
            } else {
                *share = (*share - step).max(0.0);
                *share > 0.0
            }
        });
    }

    /// The share of the pixels where tiles give way to the scans on their surface:
    /// the largest tile's (0 when no scans are shown).
    pub fn share(&self) -> f32 {
        self.shares.values().copied().fold(0.0, f32::max)
    }

    /// How far one tile's scans have faded in (0 when not shown).
    pub fn tile_share(&self, id: TileId) -> f32 {
        self.shares.get(&id).copied().unwrap_or(0.0)
    }

    /// Tiles whose scans are shown (share above 0), with their shares.
    pub fn shown(&self) -> impl Iterator<Item = (TileId, f32)> + '_ {
        self.shares.iter().map(|(id, s)| (*id, *s))
    }

    pub fn is_empty(&self) -> bool {
        self.shares.is_empty()
    }
}

/// What a hybrid frame drew.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct HybridStats {
    /// Scans the tiles wanted below them.
    pub scans_wanted: usize,
    /// The scan frame, when scans were drawn.
    pub scans: Option<FrameStats>,
}

impl<S: TileSource> TileRenderer<S> {
    /// Records and submits one hybrid frame into `target` (after [`Self::update`]):
    /// the `wanted` scans (see [`Self::scans_wanted`]; those `renderer` holds are
    /// drawn) through the scan renderer with `settings`, then the tiles over them
    /// with `depth` (`DEPTH_FORMAT`, the target's size). Without wanted scans, or
    /// when the scans' mode keeps no nearest-distance target (the painter), the tiles
    /// are drawn alone, cleared to the background.
    pub fn encode_over_scans(
        &mut self,
        renderer: &mut Renderer,
        settings: &RenderSettings,
        wanted: &BTreeSet<ScanId>,
        camera: &VirtualCamera,
        target: &RenderTarget<'_>,
        depth: &wgpu::TextureView,
    ) -> Result<HybridStats, GpuError> {
        let mut stats = HybridStats {
            scans_wanted: wanted.len(),
            scans: None,
        };
        if !wanted.is_empty() {
            let mut scan_settings = settings.clone();
            scan_settings.only = Some(wanted.clone());
            scan_settings.fill_enclosed_holes = self.settings.hybrid.fill_scan_holes;
            // The tiles need the k-buffer's pre-pass: the naive layers keep none.
            if scan_settings.strategy == Strategy::NaiveLayers {
                scan_settings.strategy = Strategy::default();
            }
            stats.scans = Some(renderer.render(camera, &scan_settings, target)?);
        }
        let nearest = stats.scans.and_then(|_| renderer.scan_nearest());
        let mut encoder = self
            .gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tiles over scans"),
            });
        let pass_target = PassTarget {
            colour: *target,
            depth,
            clear: nearest.is_none().then_some(self.settings.background),
            scans: nearest,
        };
        self.encode(&mut encoder, &pass_target, camera);
        crate::gpu::submit(&self.gpu.queue, Some(encoder.finish()));
        Ok(stats)
    }

    /// One whole hybrid frame into an image: update at `now_s`, then
    /// [`Self::draw_over_scans_to_image`].
    pub fn render_over_scans_to_image(
        &mut self,
        renderer: &mut Renderer,
        settings: &RenderSettings,
        scans: &[ModelScan],
        camera: &VirtualCamera,
        now_s: f64,
    ) -> Result<(image::RgbaImage, TileFrameStats, HybridStats), TileError> {
        let tile_stats = self.update(camera, now_s);
        let (picture, stats) = self.draw_over_scans_to_image(renderer, settings, scans, camera)?;
        Ok((picture, tile_stats, stats))
    }

    /// Draws the last update's plan into an image, without updating: chooses the
    /// scans below the finest tiles from the model's `scans`, draws those `renderer`
    /// holds and the tiles over them, reads back. The caller makes the wanted scans
    /// resident (all of them, or through residency planning with
    /// `PlanOptions::only`).
    pub fn draw_over_scans_to_image(
        &mut self,
        renderer: &mut Renderer,
        settings: &RenderSettings,
        scans: &[ModelScan],
        camera: &VirtualCamera,
    ) -> Result<(image::RgbaImage, HybridStats), TileError> {
        let wanted = self.scans_wanted(scans, camera);
        let image = match self.image.take() {
            Some(t) if (t.width, t.height) == (camera.width, camera.height) => t,
            _ => ImageTarget::new(&self.gpu, camera.width, camera.height)?,
        };
        let stats = self.encode_over_scans(
            renderer,
            settings,
            &wanted,
            camera,
            &image.target(),
            image.depth_view(),
        );
        let read = stats.and_then(|s| {
            let depth = image.depth_texture();
            self.feed_back_coverage(renderer, &s, &wanted, depth, camera, scans)?;
            Ok((image.read(&self.gpu)?, s))
        });
        self.image = Some(image);
        Ok(read?)
    }

    /// Reads back the tile depth of a hybrid frame just drawn (`frame`, over the
    /// `wanted` scans; `depth` made with `COPY_SRC`) and records where the tiles
    /// still showed over ground whose scans were asked for, with the wanted scans
    /// `renderer` holds (from the model's `scans`) that did not cover it: demand for
    /// the next [`Self::scans_wanted`] (`coverage.rs`). Only when scans were drawn
    /// beneath with their nearest distances, once they have faded in fully (before,
    /// the tiles show over them by design), and when the feedback is on. Returns the
    /// points recorded.
    pub fn feed_back_coverage(
        &mut self,
        renderer: &Renderer,
        frame: &HybridStats,
        wanted: &BTreeSet<ScanId>,
        depth: &wgpu::Texture,
        camera: &VirtualCamera,
        scans: &[ModelScan],
    ) -> Result<usize, GpuError> {
        let hybrid = self.settings.hybrid;
        let scans_beneath = frame.scans.is_some() && renderer.scan_nearest().is_some();
        if !scans_beneath
            || !hybrid.enabled
            || hybrid.feedback_scans_per_tile == 0
            || self.ramp.share() < 1.0
        {
            return Ok(0);
        }
        let shown: Vec<(TileId, texel_lod::TileInfo)> = self
            .ramp
            .shown()
            .filter_map(|(id, _)| Some((id, self.index.tile(id)?)))
            .collect();
        if shown.is_empty() {
            return Ok(0);
        }
        let size = depth.size();
        let values = crate::gpu::read_depth_texture(&self.gpu.device, &self.gpu.queue, depth)?;
        let samples = depth_samples(
            &values,
            size.width,
            size.height,
            hybrid.feedback_stride_px,
            self.coverage.round(),
        );
        let drawn: BTreeSet<ScanId> = wanted
            .iter()
            .copied()
            .filter(|id| renderer.has_scan(*id))
            .collect();
        let holding = drawn_holding(scans, &drawn, hybrid.margin_m);
        Ok(self
            .coverage
            .record(&samples, camera, &shown, hybrid.feedback_cell_m, holding))
    }

    /// Demand points kept, and those given up (`coverage.rs`).
    pub fn coverage_counts(&self) -> (usize, usize) {
        self.coverage.counts()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;

    #[test]
    fn a_tile_joining_while_scans_show_starts_where_they_are() {
        let (a, b) = (TileId { lod: 0, x: 0, y: 0 }, TileId { lod: 0, x: 1, y: 0 });
        let mut ramp = ScanRamp::default();
        ramp.update(&BTreeSet::from([a]), 0.0, 0.25);
        ramp.update(&BTreeSet::from([a]), 1.0, 0.25);
        assert_eq!(ramp.share(), 1.0);
        // b joins, a leaves: the frame's share stays at 1 while a fades out.
        ramp.update(&BTreeSet::from([b]), 1.1, 0.25);
        assert_eq!(ramp.tile_share(b), 1.0);
        assert!(ramp.tile_share(a) < 1.0 && ramp.tile_share(a) > 0.0);
        assert_eq!(ramp.share(), 1.0);
        assert_eq!(ramp.shown().count(), 2);
    }

    #[test]
    fn shares_fade_in_and_out_over_the_fade_time() {
        let a = TileId { lod: 0, x: 1, y: 2 };
        let mut ramp = ScanRamp::default();
        ramp.update(&BTreeSet::from([a]), 0.0, 0.25);
        assert!(ramp.tile_share(a) > 0.0 && ramp.tile_share(a) < 1e-3);
        ramp.update(&BTreeSet::from([a]), 0.125, 0.25);
        assert!(
            (ramp.tile_share(a) - 0.5).abs() < 1e-3,
            "{}",
            ramp.tile_share(a)
        );
        ramp.update(&BTreeSet::from([a]), 1.0, 0.25);
        assert_eq!(ramp.tile_share(a), 1.0);
        ramp.update(&BTreeSet::new(), 1.125, 0.25);
        assert!((ramp.tile_share(a) - 0.5).abs() < 1e-3);
        ramp.update(&BTreeSet::new(), 2.0, 0.25);
        assert_eq!(ramp.tile_share(a), 0.0);
        assert!(ramp.is_empty());
        // No fade: at once; time going backwards or NaN never gives NaN.
        ramp.update(&BTreeSet::from([a]), 2.0, 0.0);
        assert_eq!(ramp.tile_share(a), 1.0);
        ramp.update(&BTreeSet::new(), f64::NAN, f64::NAN);
        assert!(ramp.is_empty());
    }
}
