//! The scans below the finest tiles (Liu 2014 §3: the tree's leaves are the scans
//! themselves): which finest tiles show their scans and how far the switch has faded
//! in ([`ScanRamp`]), and which scans to draw for them ([`scans_below`]): per tile, the
//! scans whose bounds reach it, most reliable for the current view first (Killpack &
//! Budge 2016 §3's point-of-view and range confidences, taken at the tile's centre),
//! at most a few per tile. The scans are drawn first with view-dependent blending;
//! the tile pass then draws over them, giving way on their surface (`tile.wgsl`), so
//! a tile still fills wherever the chosen scans did not reach: no hole. Every tile
//! gives way where scans drew, not only those that asked for them: the scans are
//! drawn anyway and carry the EO images' detail.

use std::collections::{BTreeMap, BTreeSet};

use glam::DVec3;
use nalgebra::Point3;
use texel::model::{ModelScan, ScanId};
use texel_lod::{TileId, TileInfo};

use super::image_target::ImageTarget;
use super::pass::PassTarget;
use super::source::TileSource;
use super::{TileError, TileFrameStats, TileRenderer};
use crate::camera::VirtualCamera;
use crate::cull::{ScanBounds, Visibility, classify};
use crate::gpu::{FrameStats, GpuError, RenderSettings, RenderTarget, Renderer, Strategy};

/// How the scans below the finest tiles are chosen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HybridSettings {
    /// Draw the scans below finest tiles the view still finds too coarse.
    pub enabled: bool,
    /// Scans drawn per such tile, nearest-acquired first: more fill more of the tile
    /// with scan detail and cost a scan pass each.
    pub scans_per_tile: usize,
    /// A scan counts for a tile when its bounds come this close, metres.
    pub margin_m: f64,
}

impl Default for HybridSettings {
    fn default() -> Self {
        Self {
            enabled: true,
            scans_per_tile: 8,
            margin_m: 0.5,
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

/// Whether the scan renderer would draw the scan from `camera` (judged from its
/// listing, which bounds its data).
fn drawn_from(scan: &ModelScan, camera: &VirtualCamera) -> bool {
    let Some(bounds) = ScanBounds::of_listing(&scan.listing) else {
        return false;
    };
    let cop = DVec3::from_array(scan.listing.cop_m.map(f64::from));
    classify(&bounds, cop, &scan.world_from_scan, camera) == Visibility::Visible
}

/// A scan's world bounds (its listing's box through its pose) and acquisition centre.
struct WorldBox {
    lo: [f64; 3],
    hi: [f64; 3],
    cop: [f64; 3],
}

fn world_box(scan: &ModelScan) -> Option<WorldBox> {
    let (lo, hi) = (scan.listing.bounds_min_m, scan.listing.bounds_max_m);
    if !(lo.iter().chain(&hi).all(|c| c.is_finite()) && (0..3).all(|a| lo[a] <= hi[a])) {
        return None;
    }
    let mut min = [f64::INFINITY; 3];
    let mut max = [f64::NEG_INFINITY; 3];
    for k in 0..8 {
        let pick = |a: usize| f64::from(if k >> a & 1 == 0 { lo[a] } else { hi[a] });
        let p = scan.world_from_scan * Point3::new(pick(0), pick(1), pick(2));
        for a in 0..3 {
            min[a] = min[a].min(p[a]);
            max[a] = max[a].max(p[a]);
        }
    }
    let cop = scan.listing.cop_m.map(f64::from);
    let cop = scan.world_from_scan * Point3::new(cop[0], cop[1], cop[2]);
    let ok = min.iter().chain(&max).all(|c| c.is_finite());
    ok.then_some(WorldBox {
        lo: min,
        hi: max,
        cop: [cop.x, cop.y, cop.z],
    })
}

/// How reliable a scan acquired at `cop_m` is for a view from `eye_m` of a surface
/// at `at_m` (Killpack & Budge 2016 §3 without the per-triangle accuracy): the
/// point-of-view confidence (cosine between the directions to the two centres of
/// projection, 0 when opposite) times the range confidence
/// `min(1, d_virtual / d_acquisition)`. 0 for a degenerate geometry.
pub fn view_reliability(cop_m: [f64; 3], eye_m: [f64; 3], at_m: [f64; 3]) -> f64 {
    let to_cop = [0, 1, 2].map(|a| cop_m[a] - at_m[a]);
    let to_eye = [0, 1, 2].map(|a| eye_m[a] - at_m[a]);
    let norm = |v: [f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let (d_acquisition, d_virtual) = (norm(to_cop), norm(to_eye));
    // Guard: a centre of projection on the surface point has no direction.
    if !(d_acquisition > 1e-9 && d_virtual > 1e-9) {
        return 0.0;
    }
    let cos = (0..3).map(|a| to_cop[a] * to_eye[a]).sum::<f64>() / (d_acquisition * d_virtual);
    let pov = cos.clamp(0.0, 1.0);
    let range = (d_virtual / d_acquisition).min(1.0);
    let r = pov * range;
    if r.is_finite() { r } else { 0.0 }
}

/// The scans to draw below `tiles` (finest tiles whose scans are shown): for each,
/// the `settings.scans_per_tile` scans whose world bounds come within the margin of
/// the tile's and that the scan renderer would draw from `camera` (not culled:
/// `crate::cull`), most reliable for the camera's view of the tile's centre first
/// ([`view_reliability`]; ties to the nearest acquisition, then the lower id).
pub fn scans_below(
    tiles: &[TileInfo],
    scans: &[ModelScan],
    camera: &VirtualCamera,
    settings: &HybridSettings,
) -> BTreeSet<ScanId> {
    let eye = camera.world_from_eo.translation.vector;
    let eye_m = [eye.x, eye.y, eye.z];
    let mut chosen = BTreeSet::new();
    if tiles.is_empty() || settings.scans_per_tile == 0 {
        return chosen;
    }
    let boxes: Vec<(ScanId, WorldBox)> = scans
        .iter()
        .filter(|s| drawn_from(s, camera))
        .filter_map(|s| Some((s.id, world_box(s)?)))
        .collect();
    let margin = settings.margin_m.max(0.0);
    for tile in tiles {
        let centre = [0, 1, 2].map(|a| 0.5 * (tile.bounds_min_m[a] + tile.bounds_max_m[a]));
        let mut ranked: Vec<(f64, f64, ScanId)> = boxes
            .iter()
            .filter(|(_, WorldBox { lo, hi, .. })| {
                (0..3).all(|a| {
                    lo[a] <= tile.bounds_max_m[a] + margin && hi[a] >= tile.bounds_min_m[a] - margin
                })
            })
            .map(|(id, WorldBox { cop, .. })| {
                let d2 = (0..3).map(|a| (cop[a] - eye_m[a]).powi(2)).sum::<f64>();
                (view_reliability(*cop, eye_m, centre), d2, *id)
            })
            .collect();
        ranked.sort_by(|a, b| {
            b.0.total_cmp(&a.0)
                .then(a.1.total_cmp(&b.1))
                .then(a.2.cmp(&b.2))
        });
        chosen.extend(
            ranked
                .into_iter()
                .take(settings.scans_per_tile)
                .map(|(_, _, id)| id),
        );
    }
    chosen
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
        self.gpu.queue.submit(Some(encoder.finish()));
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
        let read = stats.and_then(|s| Ok((image.read(&self.gpu)?, s)));
        self.image = Some(image);
        Ok(read?)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;
    use texel::Pose;
    use texel::model::ScanListing;

    fn scan(id: u64, x_m: f64) -> ModelScan {
        ModelScan {
            id,
            scan: None,
            listing: ScanListing {
                timestamp_ns: 0,
                bounds_min_m: [-1.0, -1.0, 1.0],
                bounds_max_m: [1.0, 1.0, 5.0],
                cop_m: [0.0; 3],
                priority: 0.0,
                encoded_bytes: 0,
            },
            world_from_scan: Pose::translation(x_m, 0.0, 0.0),
            revisions: 0,
        }
    }

    /// A camera 30 m behind the scans' centres at `x_m`, looking the way they look
    /// (+z), 90 degrees across.
    fn camera(x_m: f64) -> VirtualCamera {
        VirtualCamera::new(Pose::translation(x_m, 0.0, -30.0), 90.0, 100, 100).unwrap()
    }

    fn tile(x0: f64, x1: f64) -> TileInfo {
        TileInfo {
            bounds_min_m: [x0, -5.0, 0.0],
            bounds_max_m: [x1, 5.0, 6.0],
            geometric_error_m: 0.05,
        }
    }

    #[test]
    fn each_tile_gets_the_scans_reaching_it_most_reliable_for_the_view() {
        let scans: Vec<ModelScan> = (0..20u32)
            .map(|i| scan(u64::from(i), f64::from(i)))
            .collect();
        let settings = HybridSettings {
            scans_per_tile: 3,
            margin_m: 0.0,
            ..HybridSettings::default()
        };
        // Scans at x = 0..19, each 2 m wide: the tile [10, 12] is reached by 9..=13.
        let got = scans_below(&[tile(10.0, 12.0)], &scans, &camera(30.0), &settings);
        assert_eq!(got, BTreeSet::from([11u64, 12, 13]));
        let got = scans_below(&[tile(10.0, 12.0)], &scans, &camera(0.0), &settings);
        assert_eq!(got, BTreeSet::from([9u64, 10, 11]));
        // Two tiles: the union.
        let got = scans_below(
            &[tile(0.0, 1.0), tile(10.0, 12.0)],
            &scans,
            &camera(0.0),
            &settings,
        );
        assert_eq!(got.len(), 6);
        assert!(scans_below(&[], &scans, &camera(0.0), &settings).is_empty());
        // Scans the renderer would cull are never chosen: one behind the camera, one
        // looking back at it (the camera sees its back); all reach a tall tile.
        let tall = TileInfo {
            bounds_min_m: [10.0, -5.0, -50.0],
            bounds_max_m: [12.0, 5.0, 50.0],
            geometric_error_m: 0.05,
        };
        let mut behind = scan(40, 11.0);
        behind.world_from_scan = Pose::translation(11.0, 0.0, -40.0);
        let mut back = scan(41, 11.0);
        back.world_from_scan = Pose::from_parts(
            nalgebra::Translation3::new(11.0, 0.0, 20.0),
            nalgebra::UnitQuaternion::from_euler_angles(0.0, std::f64::consts::PI, 0.0),
        );
        let cam = camera(11.0);
        for (s, want) in [
            (&behind, Visibility::OutsideFrustum),
            (&back, Visibility::FacingAway),
        ] {
            let bounds = ScanBounds::of_listing(&s.listing).unwrap();
            let cop = DVec3::from_array(s.listing.cop_m.map(f64::from));
            assert_eq!(classify(&bounds, cop, &s.world_from_scan, &cam), want);
        }
        let got = scans_below(&[tall], &[behind, back, scan(42, 11.0)], &cam, &settings);
        assert_eq!(got, BTreeSet::from([42u64]));
    }

    #[test]
    fn reliability_is_the_view_and_range_confidence() {
        let at = [0.0, 0.0, 0.0];
        // Seen from where it was acquired: 1.
        assert!((view_reliability([0.0, 0.0, 5.0], [0.0, 0.0, 5.0], at) - 1.0).abs() < 1e-12);
        // Acquired twice as far: half (range confidence); closer: still 1.
        assert!((view_reliability([0.0, 0.0, 10.0], [0.0, 0.0, 5.0], at) - 0.5).abs() < 1e-12);
        assert!((view_reliability([0.0, 0.0, 2.0], [0.0, 0.0, 5.0], at) - 1.0).abs() < 1e-12);
        // 60 degrees apart: cos = 0.5; from behind: 0.
        let side = [
            5.0 * 60f64.to_radians().sin(),
            0.0,
            5.0 * 60f64.to_radians().cos(),
        ];
        assert!((view_reliability(side, [0.0, 0.0, 5.0], at) - 0.5).abs() < 1e-12);
        assert_eq!(view_reliability([0.0, 0.0, -5.0], [0.0, 0.0, 5.0], at), 0.0);
        // Degenerate: a centre on the point, or not finite.
        assert_eq!(view_reliability(at, [0.0, 0.0, 5.0], at), 0.0);
        assert_eq!(view_reliability([f64::NAN; 3], [0.0, 0.0, 5.0], at), 0.0);
        assert_eq!(
            view_reliability([0.0, 0.0, f64::INFINITY], [0.0, 0.0, 5.0], at),
            0.0
        );
    }

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
    fn a_scan_with_a_broken_listing_is_never_chosen() {
        let mut bad = scan(1, 10.0);
        bad.listing.bounds_min_m = [f32::NAN, 0.0, 0.0];
        let mut inverted = scan(2, 10.0);
        inverted.listing.bounds_min_m = [2.0, 2.0, 2.0];
        let got = scans_below(
            &[tile(0.0, 20.0)],
            &[bad, inverted, scan(3, 10.0)],
            &camera(10.0),
            &HybridSettings::default(),
        );
        assert_eq!(got, BTreeSet::from([3u64]));
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
