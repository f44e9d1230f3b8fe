//! The on-disk layout of a scene file (TOML). Every table refuses unknown keys;
//! values that later checks refer to keep their byte spans so errors can name the
//! line. Defaults live here, in code; `docs/simulator.md` is the reference.

use std::collections::BTreeMap;

use serde::Deserialize;
use toml::Spanned;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct SceneFile {
    #[serde(default)]
    pub name: Option<String>,
    /// Sensor file, relative to the scene file.
    pub sensor: Spanned<String>,
    #[serde(default)]
    pub effects: Vec<Spanned<toml::Value>>,
    /// Linear RGB radiance of rays that hit nothing.
    #[serde(default)]
    pub background: [f32; 3],
    pub trajectory: Spanned<TrajectoryFile>,
    #[serde(default)]
    pub materials: BTreeMap<String, Spanned<MaterialFile>>,
    #[serde(default)]
    pub objects: ObjectsFile,
    #[serde(default)]
    pub lights: LightsFile,
}

fn default_rate_hz() -> f64 {
    10.0
}

fn default_start_time_s() -> f64 {
    1.0
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct TrajectoryFile {
    #[serde(default = "default_rate_hz")]
    pub rate_hz: f64,
    /// Timestamp of frame 0, seconds.
    #[serde(default = "default_start_time_s")]
    pub start_time_s: f64,
    #[serde(default)]
    pub frames: Option<Spanned<u64>>,
    #[serde(default)]
    pub orbit: Option<Spanned<OrbitFile>>,
    #[serde(default)]
    pub handheld: Option<Spanned<HandheldFile>>,
    #[serde(default)]
    pub poses: Option<Spanned<Vec<Spanned<PoseFile>>>>,
}

fn default_arc_deg() -> f64 {
    360.0
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct OrbitFile {
    pub center: [f64; 3],
    pub radius_m: f64,
    #[serde(default)]
    pub height_m: f64,
    #[serde(default)]
    pub look_at: Option<[f64; 3]>,
    #[serde(default)]
    pub start_deg: f64,
    #[serde(default = "default_arc_deg")]
    pub arc_deg: f64,
}

fn default_speed() -> f64 {
    0.5
}
fn default_jitter_position() -> f64 {
    0.005
}
fn default_jitter_rotation() -> f64 {
    0.3
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct HandheldFile {
    pub waypoints: Vec<[f64; 3]>,
    #[serde(default)]
    pub look_at: Option<[f64; 3]>,
    #[serde(default = "default_speed")]
    pub speed_m_per_s: f64,
    #[serde(default = "default_jitter_position")]
    pub jitter_position_m: f64,
    #[serde(default = "default_jitter_rotation")]
    pub jitter_rotation_deg: f64,
    #[serde(default)]
    pub seed: u64,
    /// The operator sweeping the camera left and right about the vertical.
    #[serde(default)]
    pub pan: Option<PanFile>,
    /// Without `look_at`: the view tilted above (positive) or below (negative) the
    /// path's direction, degrees.
    #[serde(default)]
    pub pitch_deg: f64,
}

#[derive(Debug, Deserialize, Clone, Copy)]
#[serde(deny_unknown_fields)]
pub(crate) struct PanFile {
    pub amplitude_deg: f64,
    pub period_s: f64,
    /// Where in the sweep the walk starts: 90 starts fully to the left.
    #[serde(default)]
    pub phase_deg: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct PoseFile {
    pub position: [f64; 3],
    #[serde(default)]
    pub rotation_xyzw: Option<[f64; 4]>,
    #[serde(default)]
    pub look_at: Option<[f64; 3]>,
    /// With `look_at`: rotation about the optical axis, degrees (clockwise in the image).
    #[serde(default)]
    pub roll_deg: f64,
}

fn default_shininess() -> f32 {
    32.0
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct MaterialFile {
    #[serde(default)]
    pub color: Option<[f32; 3]>,
    #[serde(default)]
    pub checker: Option<CheckerFile>,
    #[serde(default)]
    pub image: Option<ImageFile>,
    #[serde(default)]
    pub noise: Option<NoiseFile>,
    #[serde(default)]
    pub bricks: Option<BricksFile>,
    #[serde(default)]
    pub specular: f32,
    #[serde(default = "default_shininess")]
    pub shininess: f32,
    #[serde(default)]
    pub lidar_reflectivity: Option<f32>,
}

fn white() -> [f32; 3] {
    [1.0; 3]
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct CheckerFile {
    pub colors: [[f32; 3]; 2],
    pub square_m: f64,
    #[serde(default)]
    pub squares: Option<[u32; 2]>,
    #[serde(default = "white")]
    pub border: [f32; 3],
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ImageFile {
    pub file: Spanned<String>,
    pub size_m: [f64; 2],
}

fn default_octaves() -> u32 {
    6
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct NoiseFile {
    pub palette: Vec<[f32; 3]>,
    pub scale_m: f64,
    #[serde(default = "default_octaves")]
    pub octaves: u32,
    #[serde(default)]
    pub seed: u64,
}

fn default_brick_variation() -> f32 {
    0.1
}

fn default_mortar_color() -> [f32; 3] {
    [0.62, 0.6, 0.56]
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct BricksFile {
    /// Length and height of a brick with its share of the joints, metres.
    pub brick_m: [f64; 2],
    /// Width of the mortar joints, metres.
    pub mortar_m: f64,
    pub palette: Vec<[f32; 3]>,
    /// Brightness variation from brick to brick, relative.
    #[serde(default = "default_brick_variation")]
    pub variation: f32,
    #[serde(default = "default_mortar_color")]
    pub mortar_color: [f32; 3],
    #[serde(default)]
    pub seed: u64,
}

/// Objects, grouped by kind: `[[objects.box]]`, `[[objects.plane]]`, ...
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ObjectsFile {
    #[serde(default)]
    pub plane: Vec<Spanned<PlaneFile>>,
    #[serde(default, rename = "box")]
    pub boxes: Vec<Spanned<BoxFile>>,
    #[serde(default)]
    pub sphere: Vec<Spanned<SphereFile>>,
    #[serde(default)]
    pub cylinder: Vec<Spanned<CylinderFile>>,
    #[serde(default)]
    pub mesh: Vec<Spanned<MeshFile>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct PlaneFile {
    #[serde(default)]
    pub name: Option<String>,
    pub material: Spanned<String>,
    /// False for objects that can never shadow anything (the walls of a convex room
    /// lit from inside): shadow rays then skip them.
    #[serde(default = "yes")]
    pub casts_shadows: bool,
    #[serde(default)]
    pub position: [f64; 3],
    #[serde(default)]
    pub rotation_deg: [f64; 3],
    /// Width and height along the local x and y axes; absent = unbounded.
    #[serde(default)]
    pub size: Option<[f64; 2]>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct BoxFile {
    #[serde(default)]
    pub name: Option<String>,
    pub material: Spanned<String>,
    /// False for objects that can never shadow anything (the walls of a convex room
    /// lit from inside): shadow rays then skip them.
    #[serde(default = "yes")]
    pub casts_shadows: bool,
    #[serde(default)]
    pub position: [f64; 3],
    #[serde(default)]
    pub rotation_deg: [f64; 3],
    pub size: [f64; 3],
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct SphereFile {
    #[serde(default)]
    pub name: Option<String>,
    pub material: Spanned<String>,
    /// False for objects that can never shadow anything (the walls of a convex room
    /// lit from inside): shadow rays then skip them.
    #[serde(default = "yes")]
    pub casts_shadows: bool,
    #[serde(default)]
    pub position: [f64; 3],
    #[serde(default)]
    pub rotation_deg: [f64; 3],
    pub radius: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct CylinderFile {
    #[serde(default)]
    pub name: Option<String>,
    pub material: Spanned<String>,
    /// False for objects that can never shadow anything (the walls of a convex room
    /// lit from inside): shadow rays then skip them.
    #[serde(default = "yes")]
    pub casts_shadows: bool,
    #[serde(default)]
    pub position: [f64; 3],
    #[serde(default)]
    pub rotation_deg: [f64; 3],
    pub radius: f64,
    pub height: f64,
}

fn one() -> f64 {
    1.0
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct MeshFile {
    #[serde(default)]
    pub name: Option<String>,
    pub material: Spanned<String>,
    /// False for objects that can never shadow anything (the walls of a convex room
    /// lit from inside): shadow rays then skip them.
    #[serde(default = "yes")]
    pub casts_shadows: bool,
    #[serde(default)]
    pub position: [f64; 3],
    #[serde(default)]
    pub rotation_deg: [f64; 3],
    pub file: Spanned<String>,
    #[serde(default = "one")]
    pub scale: f64,
}

fn default_ambient() -> [f32; 3] {
    [0.2; 3]
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct LightsFile {
    #[serde(default = "default_ambient")]
    pub ambient: [f32; 3],
    #[serde(default)]
    pub directional: Vec<Spanned<DirectionalFile>>,
    #[serde(default)]
    pub point: Vec<Spanned<PointFile>>,
}

impl Default for LightsFile {
    fn default() -> Self {
        Self {
            ambient: default_ambient(),
            directional: Vec::new(),
            point: Vec::new(),
        }
    }
}

fn yes() -> bool {
    true
}
fn one_f32() -> f32 {
    1.0
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct DirectionalFile {
    /// The direction the light travels in.
    pub direction: [f64; 3],
    #[serde(default = "white")]
    pub color: [f32; 3],
    #[serde(default = "one_f32")]
    pub intensity: f32,
    #[serde(default = "yes")]
    pub shadows: bool,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct PointFile {
    pub position: [f64; 3],
    #[serde(default = "white")]
    pub color: [f32; 3],
    /// Irradiance at 1 m.
    #[serde(default = "one_f32")]
    pub intensity: f32,
    #[serde(default = "yes")]
    pub shadows: bool,
}
