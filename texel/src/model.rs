//! The texel model: an append-only log of scans and their revisable poses, as the
//! daemon builds it and every viewer replicates it from the stream.

use std::sync::Arc;

use crate::pose::Pose;
use crate::scan::TexelScan;

/// Identifies a scan within one model (assigned in insertion order from 0).
pub type ScanId = u64;

/// A change to the model.
#[derive(Debug, Clone)]
pub enum ModelEvent {
    /// A registered scan joins the model.
    ScanAdded {
        id: ScanId,
        scan: Arc<TexelScan>,
        world_from_scan: Pose,
    },
    /// Global refinement moved a scan.
    PoseRevised { id: ScanId, world_from_scan: Pose },
}

/// One scan of the model with its current pose.
#[derive(Debug, Clone)]
pub struct ModelScan {
    pub id: ScanId,
    pub scan: Arc<TexelScan>,
    pub world_from_scan: Pose,
    /// How many times the pose was revised.
    pub revisions: u32,
}

/// Why an event could not be applied.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ModelError {
    #[error("scan {got} added out of order (expected id {expected})")]
    OutOfOrder { expected: ScanId, got: ScanId },
    #[error("pose revision for unknown scan {0}")]
    UnknownScan(ScanId),
}

/// The model's current state.
#[derive(Debug, Clone, Default)]
pub struct Model {
    scans: Vec<ModelScan>,
    events_applied: u64,
}

impl Model {
    pub fn new() -> Self {
        Self::default()
    }

    /// Applies one event; ids must arrive in order, revisions must name known scans.
    pub fn apply(&mut self, event: ModelEvent) -> Result<(), ModelError> {
        match event {
            ModelEvent::ScanAdded {
                id,
                scan,
                world_from_scan,
            } => {
                let expected = self.scans.len() as ScanId;
                if id != expected {
                    return Err(ModelError::OutOfOrder { expected, got: id });
                }
                self.scans.push(ModelScan {
                    id,
                    scan,
                    world_from_scan,
                    revisions: 0,
                });
            }
            ModelEvent::PoseRevised {
                id,
                world_from_scan,
            } => {
                let entry = usize::try_from(id)
                    .ok()
                    .and_then(|i| self.scans.get_mut(i))
                    .ok_or(ModelError::UnknownScan(id))?;
                entry.world_from_scan = world_from_scan;
                entry.revisions += 1;
            }
        }
        self.events_applied += 1;
        Ok(())
    }

    /// The id the next added scan gets.
    pub fn next_id(&self) -> ScanId {
        self.scans.len() as ScanId
    }

    pub fn scans(&self) -> &[ModelScan] {
        &self.scans
    }

    pub fn get(&self, id: ScanId) -> Option<&ModelScan> {
        usize::try_from(id).ok().and_then(|i| self.scans.get(i))
    }

    pub fn len(&self) -> usize {
        self.scans.len()
    }

    pub fn is_empty(&self) -> bool {
        self.scans.is_empty()
    }

    pub fn events_applied(&self) -> u64 {
        self.events_applied
    }

    /// The events that rebuild this model's current state from nothing (one
    /// `ScanAdded` per scan, at its current pose): what a late viewer receives first.
    pub fn snapshot(&self) -> impl Iterator<Item = ModelEvent> + '_ {
        self.scans.iter().map(|s| ModelEvent::ScanAdded {
            id: s.id,
            scan: Arc::clone(&s.scan),
            world_from_scan: s.world_from_scan,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frames::EoFrame;
    use crate::sensor::RangeNoise;

    fn scan() -> Arc<TexelScan> {
        Arc::new(TexelScan {
            timestamp_ns: 0,
            seq: 0,
            grid_width: 0,
            grid_height: 0,
            vertices: vec![],
            tex_coords: vec![],
            vertex_textured: vec![],
            vertex_pixel: vec![],
            pixel_vertex: vec![],
            triangles: vec![],
            triangle_accuracy: vec![],
            triangle_flags: vec![],
            texture: std::sync::Arc::new(EoFrame {
                width: 1,
                height: 1,
                rgb: vec![0; 3],
                timestamp_ns: 0,
            }),
            cop_m: [0.0; 3],
            scan_from_lidar: Pose::identity(),
            range_noise: RangeNoise::default(),
        })
    }

    #[test]
    fn events_build_the_model_and_snapshots_rebuild_it() {
        let mut m = Model::new();
        let p = |x: f64| Pose::translation(x, 0.0, 0.0);
        m.apply(ModelEvent::ScanAdded {
            id: 0,
            scan: scan(),
            world_from_scan: p(0.0),
        })
        .unwrap();
        m.apply(ModelEvent::ScanAdded {
            id: 1,
            scan: scan(),
            world_from_scan: p(1.0),
        })
        .unwrap();
        m.apply(ModelEvent::PoseRevised {
            id: 0,
            world_from_scan: p(0.5),
        })
        .unwrap();
        assert_eq!(
            m.apply(ModelEvent::ScanAdded {
                id: 5,
                scan: scan(),
                world_from_scan: p(0.0)
            }),
            Err(ModelError::OutOfOrder {
                expected: 2,
                got: 5
            })
        );
        assert_eq!(
            m.apply(ModelEvent::PoseRevised {
                id: 9,
                world_from_scan: p(0.0)
            }),
            Err(ModelError::UnknownScan(9))
        );
        let mut replica = Model::new();
        for e in m.snapshot() {
            replica.apply(e).unwrap();
        }
        assert_eq!(replica.len(), 2);
        assert_eq!(replica.get(0).unwrap().world_from_scan, p(0.5));
        assert_eq!(m.get(0).unwrap().revisions, 1);
    }
}
