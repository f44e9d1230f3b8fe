//! Texel's shared vocabulary: raw frames, sensor models, poses, synchronisation and the
//! capture format. No I/O beyond files, no async.

pub mod camera;
pub mod capture;
pub mod coverage;
pub mod distortion;
pub mod export;
pub mod frames;
pub mod fuse;
pub mod fusion_tables;
#[doc(hidden)]
pub mod fuzzing;
pub mod model;
pub mod paged;
pub mod pose;
pub mod radiance;
pub mod rays;
pub mod scan;
pub mod sensor;
pub mod stats;
pub mod sync;
pub mod tile;
pub mod txl1;
pub mod wire;

pub use camera::{Distortion, PinholeCamera};
pub use distortion::PlumbBob;
pub use frames::{EoExposure, EoFrame, FramePair, RangeFrame};
pub use fuse::{FuseConfig, fuse};
pub use pose::Pose;
pub use scan::{TexelScan, TriangleFlags};
pub use sensor::{RangeNoise, Sensor, SensorInfo, SensorModel};
