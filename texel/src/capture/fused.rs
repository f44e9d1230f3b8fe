//! Fusing a capture's frames: the ray tables of a sensor model are built once and
//! reused for every frame that shares it (a capture names its sensor per frame, and
//! building the tables costs far more than fusing one frame).

use std::sync::Arc;

use crate::frames::FramePair;
use crate::fuse::{FuseConfig, FuseError, fuse};
use crate::scan::TexelScan;
use crate::sensor::{Sensor, SensorModel};

/// The sensor (model and fusion tables) of the frames read so far: rebuilt only when
/// a frame comes with another sensor model.
#[derive(Debug, Default)]
pub struct SensorCache {
    current: Option<(Arc<SensorModel>, Sensor)>,
}

impl SensorCache {
    pub fn new() -> Self {
        Self::default()
    }

    /// The sensor for `model`: the cached one when `model` is the same model (the
    /// same allocation, or an equal value), else one built now and cached.
    pub fn sensor(&mut self, model: &Arc<SensorModel>) -> &Sensor {
        let reusable = matches!(&self.current,
            Some((m, _)) if Arc::ptr_eq(m, model) || **m == **model);
        if !reusable {
            self.current = None;
        }
        let (_, sensor) = self
            .current
            .get_or_insert_with(|| (Arc::clone(model), Sensor::new((**model).clone())));
        sensor
    }

    /// Fuses `pair`, taken with `model`, into a texel scan (which keeps its EO image).
    pub fn fuse(
        &mut self,
        pair: FramePair,
        model: &Arc<SensorModel>,
        config: &FuseConfig,
    ) -> Result<TexelScan, FuseError> {
        let sensor = self.sensor(model);
        fuse(&pair.range, pair.eo, sensor, config)
    }
}
