//! Drawing the level-of-detail hierarchy (`texel-lod`): per frame, select the tiles
//! for the view with the cache's residency (Liu 2014 §4.3), ask the source for the
//! wanted ones (most needed first, a bounded number in flight), decode them off the
//! render thread, upload what finished, and draw the selection, cross-fading every
//! switch, with the scans below the finest tiles the view finds too coarse. One
//! module per job: `source.rs` (where bytes come from), `loader.rs` (the decode
//! thread), `cache.rs` (GPU tiles within a budget), `fade.rs` (the cross-fade),
//! `pass.rs` (the pipeline), `hybrid.rs` (the scans below the tiles),
//! `scan_choice.rs` (which scans those are), `coverage.rs` (where a frame still
//! showed a tile over its scans),
//! `image_target.rs` (headless targets), `measure.rs` (popping figures).

pub mod cache;
pub mod coverage;
pub mod fade;
pub mod hybrid;
pub mod image_target;
pub mod loader;
pub mod measure;
pub mod net;
pub mod pass;
pub mod scan_choice;
pub mod source;

use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

use nalgebra::{Matrix3, Matrix4, Rotation3, UnitQuaternion, Vector3};
use texel::Pose;
use texel_lod::select::in_frustum;
use texel_lod::{SelectConfig, TileId, TileIndex, TileInfo, View, select};

use self::cache::{Inserted, TileCache};
use self::coverage::CoverageFeedback;
use self::fade::{CrossFade, FadeFrame};
use self::hybrid::{HybridSettings, ScanRamp};
use self::image_target::ImageTarget;
use self::loader::{LoadOutcome, TileLoader};
use self::pass::{PassCounts, PassTarget, TileDraw, TilePass};
use self::scan_choice::{ShownTile, scans_below};
use self::source::{LoadError, TileEntry, TileSource};
use crate::camera::VirtualCamera;
use crate::gpu::{GpuContext, GpuError};

#[derive(Debug, thiserror::Error)]
pub enum TileError {
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error("cannot start the tile decode thread: {0}")]
    Thread(#[from] std::io::Error),
}

/// Frames before a tile whose load failed is asked for again (2 s at 30 Hz), unless
/// a new listing comes first.
pub const RETRY_AFTER_FRAMES: u64 = 60;

/// The tile renderer's knobs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TileSettings {
    pub select: SelectConfig,
    /// Cross-fade time of a switch, seconds (0: switch at once).
    pub fade_s: f64,
    /// GPU bytes the resident tiles may take.
    pub budget_bytes: u64,
    /// Tiles requested or decoding at once.
    pub max_in_flight: usize,
    /// Display colour where no tile is drawn.
    pub background: [f32; 3],
    /// The scans below the finest tiles.
    pub hybrid: HybridSettings,
}

impl Default for TileSettings {
    fn default() -> Self {
        Self {
            select: SelectConfig::default(),
            fade_s: 0.25,
            budget_bytes: 256 << 20,
            max_in_flight: 8,
            background: [0.0; 3],
            hybrid: HybridSettings::default(),
        }
    }
}

/// What a frame did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct TileFrameStats {
    /// Tiles drawn (the selection and tiles fading in or out).
    pub tiles_drawn: usize,
    pub triangles_drawn: u64,
    pub resident_bytes: u64,
    pub resident_tiles: usize,
    /// Tiles the selection wanted and did not have.
    pub tiles_wanted: usize,
    /// Tiles requested from the source or decoding.
    pub loads_in_flight: usize,
    /// Tiles uploaded this frame.
    pub uploaded: usize,
    /// The selection differs from the previous frame's.
    pub selection_changed: bool,
    /// A cross-fade is under way.
    pub fading: bool,
    /// Finest tiles showing the scans below them (see [`TileRenderer::scans_wanted`]).
    pub tiles_with_scans: usize,
}

/// The listing as selection sees it; the top tiles are those of the highest level
/// listed (as `Hierarchy::roots`).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ListingIndex {
    pub tiles: BTreeMap<TileId, TileEntry>,
    top_lod: Option<u8>,
}

impl ListingIndex {
    pub fn new(entries: impl IntoIterator<Item = TileEntry>) -> Self {
        let tiles: BTreeMap<TileId, TileEntry> = entries.into_iter().map(|e| (e.id, e)).collect();
        let top_lod = tiles.keys().map(|id| id.lod).max();
        Self { tiles, top_lod }
    }
}

impl TileIndex for ListingIndex {
    fn roots(&self) -> Vec<TileId> {
        self.tiles
            .keys()
            .filter(|id| Some(id.lod) == self.top_lod)
            .copied()
            .collect()
    }

    fn tile(&self, id: TileId) -> Option<TileInfo> {
        self.tiles.get(&id).map(|e| e.info)
    }
}

/// A camera pose at `eye_m` looking at `target_m` with `up` (world) up on screen, in
/// the viewer's optical frame (x right, y down, z forward). `None` when degenerate.
pub fn look_at(eye_m: [f64; 3], target_m: [f64; 3], up: [f64; 3]) -> Option<Pose> {
    let z = (Vector3::from(target_m) - Vector3::from(eye_m)).try_normalize(1e-12)?;
    let x = z.cross(&Vector3::from(up)).try_normalize(1e-12)?;
    let y = z.cross(&x);
    let rotation = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Some(Pose::from_parts(
        nalgebra::Translation3::from(Vector3::from(eye_m)),
        UnitQuaternion::from_rotation_matrix(&rotation),
    ))
}

/// The camera as selection sees it: eye-relative clip coordinates in f64 (reverse z,
/// far plane at infinity, as the passes draw).
pub fn lod_view(camera: &VirtualCamera) -> View {
    let fy = 1.0 / camera.tan_half_fov_y();
    let fx = fy / camera.aspect();
    #[rustfmt::skip]
    let clip_from_view = Matrix4::new(
        fx, 0.0, 0.0, 0.0,
        0.0, -fy, 0.0, 0.0,
        0.0, 0.0, 0.0, camera.near_m,
        0.0, 0.0, 1.0, 0.0,
    );
    let view_from_world = camera.world_from_eo.rotation.inverse().to_homogeneous();
    let eye = camera.world_from_eo.translation.vector;
    View {
        eye_m: [eye.x, eye.y, eye.z],
        clip_from_eye: clip_from_view * view_from_world,
        viewport_height_px: f64::from(camera.height),
        fov_y_rad: camera.fov_y_rad,
    }
}

/// The frame driver: source, decode thread, cache, cross-fade and pass.
pub struct TileRenderer<S: TileSource> {
    gpu: GpuContext,
    source: S,
    index: ListingIndex,
    loader: TileLoader,
    cache: TileCache,
    pass: TilePass,
    fade: CrossFade,
    /// The last update's drawing plan.
    plan: FadeFrame,
    /// Finest tiles showing their scans, and how far faded in.
    ramp: ScanRamp,
    /// Where earlier frames still showed a tile over its scans.
    coverage: CoverageFeedback,
    refined: BTreeSet<TileId>,
    last_draw: Vec<TileId>,
    /// Requested from the source, bytes not arrived yet.
    awaiting: BTreeSet<TileId>,
    /// Tiles whose last load failed, and the frame it failed in.
    failed: BTreeMap<TileId, u64>,
    frame: u64,
    /// Selection, fade and background may change between frames; the budget and
    /// the loads in flight are the cache's and loader's from construction.
    pub settings: TileSettings,
    errors: Vec<LoadError>,
    image: Option<ImageTarget>,
}

impl<S: TileSource> TileRenderer<S> {
    pub fn new(gpu: &GpuContext, source: S, settings: TileSettings) -> Result<Self, TileError> {
        Ok(Self {
            gpu: gpu.clone(),
            source,
            index: ListingIndex::default(),
            loader: TileLoader::spawn(settings.max_in_flight.max(1))?,
            cache: TileCache::new(gpu, settings.budget_bytes),
            pass: TilePass::new(gpu),
            fade: CrossFade::new(),
            plan: FadeFrame::default(),
            ramp: ScanRamp::default(),
            coverage: CoverageFeedback::default(),
            refined: BTreeSet::new(),
            last_draw: Vec::new(),
            awaiting: BTreeSet::new(),
            failed: BTreeMap::new(),
            frame: 0,
            settings,
            errors: Vec::new(),
            image: None,
        })
    }

    pub fn cache(&self) -> &TileCache {
        &self.cache
    }

    pub fn index(&self) -> &ListingIndex {
        &self.index
    }

    pub fn source_mut(&mut self) -> &mut S {
        &mut self.source
    }

    /// The tiles the last update selected (without those fading out).
    pub fn selected(&self) -> &[TileId] {
        &self.last_draw
    }

    /// Failed loads since the last call (the tiles stay wanted and are asked again
    /// after [`RETRY_AFTER_FRAMES`] or a new listing).
    pub fn take_errors(&mut self) -> Vec<LoadError> {
        std::mem::take(&mut self.errors)
    }

    /// One frame's work before drawing, at time `now_s` (seconds, for the fade):
    /// select, request, hand arrived bytes to the decoder, upload decoded tiles, plan
    /// the draw.
    pub fn update(&mut self, camera: &VirtualCamera, now_s: f64) -> TileFrameStats {
        self.frame += 1;
        let frame = self.frame;
        self.refresh_listing();
        let view = lod_view(camera);
        let cache = &self.cache;
        let selection = select(
            &self.index,
            &view,
            &|id| cache.contains(id),
            &self.refined,
            &self.settings.select,
        );
        let index = &self.index;
        let visible = |id: TileId| index.tile(id).is_some_and(|info| in_frustum(&view, &info));
        self.plan = self
            .fade
            .update(&selection.draw, &visible, now_s, self.settings.fade_s);
        let below_finest: BTreeSet<TileId> = if self.settings.hybrid.enabled {
            let planned = &self.plan.tiles;
            selection
                .below_finest
                .iter()
                .filter(|id| planned.contains_key(id))
                .copied()
                .collect()
        } else {
            BTreeSet::new()
        };
        self.ramp.update(&below_finest, now_s, self.settings.fade_s);
        let shown: BTreeSet<TileId> = self.ramp.shown().map(|(id, _)| id).collect();
        self.coverage.retain_tiles(&shown);
        // The top tiles stay resident too: without them selection has nothing to
        // start from and their ground would be empty until they load again.
        let roots = self.index.roots();
        for id in self
            .plan
            .tiles
            .keys()
            .chain(&selection.refined)
            .chain(&roots)
        {
            self.cache.mark_used(*id, frame);
        }
        // Requests: wanted tiles (most needed first), then drawn tiles with a newer
        // revision listed.
        let stale = selection.draw.iter().copied().filter(|id| {
            let listed = self.index.tiles.get(id).map(|e| e.revision);
            listed.is_some_and(|r| self.cache.revision(*id).is_some_and(|c| c < r))
        });
        let wanted: Vec<TileId> = selection.wanted.iter().copied().chain(stale).collect();
        for id in wanted {
            if self.in_flight() >= self.settings.max_in_flight.max(1) {
                break;
            }
            if self.awaiting.contains(&id) || self.loader.is_in_flight(id) {
                continue;
            }
            if self
                .failed
                .get(&id)
                .is_some_and(|f| frame < f.saturating_add(RETRY_AFTER_FRAMES))
            {
                continue;
            }
            self.awaiting.insert(id);
            self.source.request(id);
        }
        self.receive();
        let outcomes = self.loader.drain();
        let uploaded = self.upload(outcomes);
        let selection_changed = selection.draw != self.last_draw;
        self.last_draw = selection.draw;
        self.refined = selection.refined;
        let (tiles_drawn, triangles_drawn) = self
            .plan
            .tiles
            .keys()
            .filter_map(|id| self.cache.get(*id))
            .fold((0, 0u64), |(n, t), tile| {
                (n + 1, t + u64::from(tile.triangles))
            });
        TileFrameStats {
            tiles_drawn,
            triangles_drawn,
            resident_bytes: self.cache.resident_bytes(),
            resident_tiles: self.cache.len(),
            tiles_wanted: selection.wanted.len(),
            loads_in_flight: self.in_flight(),
            uploaded,
            selection_changed,
            fading: self.plan.fading,
            tiles_with_scans: self.ramp.shown().count(),
        }
    }

    /// Takes a new listing from the source, if there is one; tiles no longer listed
    /// leave the cache.
    fn refresh_listing(&mut self) {
        if let Some(listing) = self.source.poll_listing() {
            self.index = ListingIndex::new(listing);
            // A new listing may carry fixed tiles: try failed ones again.
            self.failed.clear();
            let gone: Vec<TileId> = self
                .cache
                .ids()
                .filter(|id| !self.index.tiles.contains_key(id))
                .collect();
            for id in gone {
                self.cache.remove(id);
            }
        }
    }

    /// Loads every listed tile (as the budget allows), waiting up to `timeout`: for
    /// a hierarchy small enough to hold whole, and for tests. Returns the tiles
    /// uploaded.
    pub fn preload_all(&mut self, timeout: Duration) -> usize {
        self.refresh_listing();
        let deadline = std::time::Instant::now() + timeout;
        let mut uploaded = 0;
        loop {
            let missing: Vec<TileId> = self
                .index
                .tiles
                .keys()
                .filter(|id| !self.cache.contains(**id))
                .copied()
                .collect();
            if missing.is_empty() || std::time::Instant::now() >= deadline {
                break;
            }
            for id in missing {
                if self.in_flight() >= self.settings.max_in_flight.max(1) {
                    break;
                }
                if !self.loader.is_in_flight(id) && self.awaiting.insert(id) {
                    self.source.request(id);
                }
            }
            let before = self.cache.len();
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            uploaded += self.finish_loads(left);
            if self.cache.len() == before && self.in_flight() == 0 {
                // Nothing more fits or loads (budget or errors).
                break;
            }
        }
        uploaded
    }

    fn in_flight(&self) -> usize {
        self.awaiting.len() + self.loader.in_flight()
    }

    /// Hands arrived bytes to the decoder; a full queue drops them (the tile stays
    /// wanted and is asked again next frame).
    fn receive(&mut self) {
        for arrived in self.source.receive() {
            match arrived {
                Ok(tile) => {
                    self.awaiting.remove(&tile.id);
                    let _ = self.loader.submit(tile);
                }
                Err(e) => {
                    self.awaiting.remove(&e.id);
                    self.failed.insert(e.id, self.frame);
                    self.errors.push(e);
                }
            }
        }
    }

    fn upload(&mut self, outcomes: Vec<LoadOutcome>) -> usize {
        let mut uploaded = 0;
        for outcome in outcomes {
            match outcome {
                Ok(decoded) => {
                    if !self.index.tiles.contains_key(&decoded.node.id) {
                        continue;
                    }
                    let id = decoded.node.id;
                    match self
                        .cache
                        .insert(&decoded.node, decoded.revision, self.frame)
                    {
                        Ok(Inserted::Uploaded { .. }) => {
                            uploaded += 1;
                            self.failed.remove(&id);
                        }
                        Ok(Inserted::Stale { .. } | Inserted::OverBudget { .. }) => {}
                        Err(e) => {
                            self.failed.insert(id, self.frame);
                            self.errors.push(LoadError {
                                id,
                                message: e.to_string(),
                            });
                        }
                    }
                }
                Err(e) => {
                    self.failed.insert(e.id, self.frame);
                    self.errors.push(e);
                }
            }
        }
        uploaded
    }

    /// Waits (up to `timeout`) for every request to arrive and decode, and uploads
    /// them: for tests and for a render that must be complete.
    pub fn finish_loads(&mut self, timeout: Duration) -> usize {
        let deadline = std::time::Instant::now() + timeout;
        let mut uploaded = 0;
        while self.in_flight() > 0 && std::time::Instant::now() < deadline {
            self.receive();
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            let outcomes = self.loader.wait(left.min(Duration::from_millis(20)));
            uploaded += self.upload(outcomes);
        }
        uploaded
    }

    /// The scans to draw below the finest tiles of the last update whose scans are
    /// shown (see [`scan_choice::scans_below`]; at the resident tiles' surface
    /// points), from the model's `scans`; empty when none are.
    pub fn scans_wanted(
        &self,
        scans: &[texel::model::ModelScan],
        camera: &VirtualCamera,
    ) -> BTreeSet<texel::model::ScanId> {
        let tiles: Vec<ShownTile<'_>> = self
            .ramp
            .shown()
            .filter_map(|(id, _)| {
                Some(ShownTile {
                    info: self.index.tile(id)?,
                    samples_m: self.cache.get(id).map_or(&[], |t| &t.samples_m),
                    demand: self.coverage.points(id),
                })
            })
            .collect();
        scans_below(&tiles, scans, camera, &self.settings.hybrid)
    }

    /// Records the planned tiles into `target` (see [`TilePass::encode`]).
    pub fn encode(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        target: &PassTarget<'_>,
        camera: &VirtualCamera,
    ) -> PassCounts {
        let draws: Vec<TileDraw<'_>> = self
            .plan
            .tiles
            .iter()
            .filter_map(|(id, cuts)| {
                self.cache.get(*id).map(|tile| TileDraw {
                    tile,
                    cuts: if self.plan.fading { *cuts } else { u32::MAX },
                    scan_share: self.ramp.share(),
                    surface_tolerance_m: self
                        .index
                        .tile(*id)
                        .map_or(0.0, |info| info.geometric_error_m.max(0.0) as f32),
                    scan_holes_filled: self.settings.hybrid.enabled
                        && self.settings.hybrid.fill_scan_holes,
                })
            })
            .collect();
        self.pass
            .encode(encoder, target, camera, &self.plan.ends, &draws)
    }

    /// One whole frame into an image: update, draw (cleared to the background), read
    /// back.
    pub fn render_to_image(
        &mut self,
        camera: &VirtualCamera,
        now_s: f64,
    ) -> Result<(image::RgbaImage, TileFrameStats), TileError> {
        let stats = self.update(camera, now_s);
        Ok((self.draw_to_image(camera)?, stats))
    }

    /// Draws the last update's plan from `camera` into an image, without updating
    /// (e.g. the previous frame's tiles from this frame's camera: the change a switch
    /// alone makes).
    pub fn draw_to_image(&mut self, camera: &VirtualCamera) -> Result<image::RgbaImage, TileError> {
        let image = match self.image.take() {
            Some(t) if (t.width, t.height) == (camera.width, camera.height) => t,
            _ => ImageTarget::new(&self.gpu, camera.width, camera.height)?,
        };
        let mut encoder = self
            .gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tiles"),
            });
        let background = self.settings.background;
        let target = PassTarget {
            colour: image.target(),
            depth: image.depth_view(),
            clear: Some(background),
            scans: None,
        };
        self.encode(&mut encoder, &target, camera);
        crate::gpu::submit(&self.gpu.queue, Some(encoder.finish()));
        let read = image.read(&self.gpu);
        self.image = Some(image);
        Ok(read?)
    }
}
