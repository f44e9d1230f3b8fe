//! The texel model as a viewer or the daemon holds it: every scan it knows by id
//! with its revisable pose and its listing (extent, priority, size), and the data of
//! the scans it holds. A scan can be known without its data: a viewer within a
//! memory budget keeps the data of what it shows and fetches the rest by id.

use std::sync::Arc;

use crate::pose::Pose;
use crate::scan::TexelScan;

/// Identifies a scan within one session (assigned in registration order from 0; a
/// model may hold any subset of the ids, since retired scans leave it).
pub type ScanId = u64;

/// What a model knows of a scan without its data: enough to cull it, to order it
/// and to decide whether to ask for it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanListing {
    /// The range frame's timestamp.
    pub timestamp_ns: u64,
    /// Axis-aligned bounds of the scan's vertices in its own frame.
    pub bounds_min_m: [f32; 3],
    pub bounds_max_m: [f32; 3],
    /// The acquisition centre of projection in the scan's own frame.
    pub cop_m: [f32; 3],
    /// How much the scan shows, reliability-weighted (`texel::coverage`): larger is
    /// fetched and drawn first. 0 when unknown.
    pub priority: f32,
    /// Bytes of its `ScanAdded` frame on the wire (0 when unknown).
    pub encoded_bytes: u64,
}

impl ScanListing {
    /// The listing of a scan's data. Non-finite vertices are skipped; a scan without
    /// a finite vertex gets empty bounds at its centre of projection.
    pub fn of_scan(scan: &TexelScan, encoded_bytes: u64, priority: f32) -> Self {
        let mut min = [f32::INFINITY; 3];
        let mut max = [f32::NEG_INFINITY; 3];
        for v in scan
            .vertices
            .iter()
            .filter(|v| v.iter().all(|c| c.is_finite()))
        {
            for k in 0..3 {
                min[k] = min[k].min(v[k]);
                max[k] = max[k].max(v[k]);
            }
        }
        let cop_m = scan
            .cop_m
            .map(|c| if c.is_finite() { c as f32 } else { 0.0 });
        if min.iter().any(|c| !c.is_finite()) {
            min = cop_m;
            max = cop_m;
        }
        Self {
            timestamp_ns: scan.timestamp_ns,
            bounds_min_m: min,
            bounds_max_m: max,
            cop_m,
            priority: if priority.is_finite() { priority } else { 0.0 },
            encoded_bytes,
        }
    }
}

/// A change to the model.
#[derive(Debug, Clone)]
pub enum ModelEvent {
    /// A scan's data arrives: a newly registered scan, or one fetched by id. A scan
    /// not yet known is listed from its data.
    ScanAdded {
        id: ScanId,
        scan: Arc<TexelScan>,
        world_from_scan: Pose,
    },
    /// Global refinement moved a scan.
    PoseRevised { id: ScanId, world_from_scan: Pose },
    /// A scan is known (without its data, or its data is kept if held): a late
    /// joiner's snapshot, or a retired scan that is useful again.
    ScanListed {
        id: ScanId,
        listing: ScanListing,
        world_from_scan: Pose,
    },
    /// The scan left the served model (retired as redundant): forget it.
    ScanWithdrawn { id: ScanId },
    /// This model dropped the scan's data to stay within a budget; it stays listed
    /// and can be fetched again.
    ScanEvicted { id: ScanId },
}

impl ModelEvent {
    /// The scan the event concerns.
    pub fn id(&self) -> ScanId {
        match self {
            Self::ScanAdded { id, .. }
            | Self::PoseRevised { id, .. }
            | Self::ScanListed { id, .. }
            | Self::ScanWithdrawn { id }
            | Self::ScanEvicted { id } => *id,
        }
    }
}

/// One scan of the model with its current pose.
#[derive(Debug, Clone)]
pub struct ModelScan {
    pub id: ScanId,
    /// The scan's data, when this model holds it.
    pub scan: Option<Arc<TexelScan>>,
    pub listing: ScanListing,
    pub world_from_scan: Pose,
    /// How many times the pose was revised.
    pub revisions: u32,
}

impl ModelScan {
    /// Whether the model holds the scan's data.
    pub fn is_resident(&self) -> bool {
        self.scan.is_some()
    }
}

/// Why an event could not be applied.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ModelError {
    #[error("{what} for unknown scan {id}")]
    UnknownScan { id: ScanId, what: &'static str },
}

/// The model's current state: scans sorted by id.
#[derive(Debug, Clone, Default)]
pub struct Model {
    scans: Vec<ModelScan>,
    resident: usize,
    events_applied: u64,
}

impl Model {
    pub fn new() -> Self {
        Self::default()
    }

    fn index(&self, id: ScanId) -> Result<usize, usize> {
        // Ids mostly arrive in increasing order: check the end first.
        match self.scans.last() {
            Some(last) if last.id < id => Err(self.scans.len()),
            None => Err(0),
            _ => self.scans.binary_search_by_key(&id, |s| s.id),
        }
    }

    fn entry(&mut self, id: ScanId, what: &'static str) -> Result<&mut ModelScan, ModelError> {
        match self.index(id) {
            Ok(i) => Ok(&mut self.scans[i]),
            Err(_) => Err(ModelError::UnknownScan { id, what }),
        }
    }

    /// Applies one event. Adding or listing a scan that is known replaces what is
    /// known of it; a revision, withdrawal or eviction must name a known scan.
    pub fn apply(&mut self, event: ModelEvent) -> Result<(), ModelError> {
        match event {
            ModelEvent::ScanAdded {
                id,
                scan,
                world_from_scan,
            } => match self.index(id) {
                Ok(i) => {
                    let entry = &mut self.scans[i];
                    if entry.scan.is_none() {
                        self.resident += 1;
                    }
                    if entry.listing.encoded_bytes == 0 {
                        entry.listing = ScanListing::of_scan(&scan, 0, entry.listing.priority);
                    }
                    entry.scan = Some(scan);
                    entry.world_from_scan = world_from_scan;
                }
                Err(i) => {
                    let listing = ScanListing::of_scan(&scan, 0, 0.0);
                    self.scans.insert(
                        i,
                        ModelScan {
                            id,
                            scan: Some(scan),
                            listing,
                            world_from_scan,
                            revisions: 0,
                        },
                    );
                    self.resident += 1;
                }
            },
            ModelEvent::PoseRevised {
                id,
                world_from_scan,
            } => {
                let entry = self.entry(id, "pose revision")?;
                entry.world_from_scan = world_from_scan;
                entry.revisions += 1;
            }
            ModelEvent::ScanListed {
                id,
                listing,
                world_from_scan,
            } => match self.index(id) {
                Ok(i) => {
                    let entry = &mut self.scans[i];
                    entry.listing = listing;
                    entry.world_from_scan = world_from_scan;
                }
                Err(i) => self.scans.insert(
                    i,
                    ModelScan {
                        id,
                        scan: None,
                        listing,
                        world_from_scan,
                        revisions: 0,
                    },
                ),
            },
            ModelEvent::ScanWithdrawn { id } => {
                let i = self.index(id).map_err(|_| ModelError::UnknownScan {
                    id,
                    what: "withdrawal",
                })?;
                if self.scans.remove(i).scan.is_some() {
                    self.resident -= 1;
                }
            }
            ModelEvent::ScanEvicted { id } => {
                let entry = self.entry(id, "eviction")?;
                if entry.scan.take().is_some() {
                    self.resident -= 1;
                }
            }
        }
        self.events_applied += 1;
        Ok(())
    }

    /// One past the largest id known (the id a locally built model gives its next scan).
    pub fn next_id(&self) -> ScanId {
        self.scans.last().map_or(0, |s| s.id.saturating_add(1))
    }

    /// Every known scan, by increasing id.
    pub fn scans(&self) -> &[ModelScan] {
        &self.scans
    }

    /// The scans whose data the model holds, by increasing id.
    pub fn resident(&self) -> impl Iterator<Item = (&ModelScan, &Arc<TexelScan>)> + '_ {
        self.scans
            .iter()
            .filter_map(|s| s.scan.as_ref().map(|scan| (s, scan)))
    }

    pub fn get(&self, id: ScanId) -> Option<&ModelScan> {
        self.index(id).ok().map(|i| &self.scans[i])
    }

    /// Known scans (listed, resident or not).
    pub fn len(&self) -> usize {
        self.scans.len()
    }

    pub fn is_empty(&self) -> bool {
        self.scans.is_empty()
    }

    /// Scans whose data the model holds.
    pub fn resident_len(&self) -> usize {
        self.resident
    }

    pub fn events_applied(&self) -> u64 {
        self.events_applied
    }

    /// The events that rebuild this model's current state from nothing: a listing
    /// per scan, then its data if held.
    pub fn snapshot(&self) -> impl Iterator<Item = ModelEvent> + '_ {
        self.scans.iter().flat_map(|s| {
            let listed = ModelEvent::ScanListed {
                id: s.id,
                listing: s.listing,
                world_from_scan: s.world_from_scan,
            };
            let data = s.scan.as_ref().map(|scan| ModelEvent::ScanAdded {
                id: s.id,
                scan: Arc::clone(scan),
                world_from_scan: s.world_from_scan,
            });
            std::iter::once(listed).chain(data)
        })
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design
    use super::*;
    use crate::frames::EoFrame;
    use crate::sensor::RangeNoise;

    fn scan(x: f32) -> Arc<TexelScan> {
        Arc::new(TexelScan {
            timestamp_ns: 7,
            seq: 0,
            grid_width: 0,
            grid_height: 0,
            vertices: vec![[x, 0.0, 1.0], [x + 1.0, 2.0, 3.0], [f32::NAN, 0.0, 0.0]],
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
                exposure: None,
            }),
            cop_m: [0.0; 3],
            scan_from_lidar: Pose::identity(),
            range_noise: RangeNoise::default(),
        })
    }

    fn p(x: f64) -> Pose {
        Pose::translation(x, 0.0, 0.0)
    }

    #[test]
    fn listings_bound_the_finite_vertices() {
        let l = ScanListing::of_scan(&scan(-1.0), 10, 2.0);
        assert_eq!(l.bounds_min_m, [-1.0, 0.0, 1.0]);
        assert_eq!(l.bounds_max_m, [0.0, 2.0, 3.0]);
        assert_eq!((l.timestamp_ns, l.encoded_bytes, l.priority), (7, 10, 2.0));
        let empty = TexelScan {
            vertices: vec![[f32::INFINITY; 3]],
            cop_m: [1.0, 2.0, f64::NAN],
            ..(*scan(0.0)).clone()
        };
        let l = ScanListing::of_scan(&empty, 0, f32::NAN);
        assert_eq!(l.bounds_min_m, [1.0, 2.0, 0.0]);
        assert_eq!(l.bounds_max_m, l.bounds_min_m);
        assert_eq!(l.priority, 0.0);
    }

    #[test]
    fn events_build_the_model_and_snapshots_rebuild_it() {
        let mut m = Model::new();
        m.apply(ModelEvent::ScanAdded {
            id: 0,
            scan: scan(0.0),
            world_from_scan: p(0.0),
        })
        .unwrap();
        m.apply(ModelEvent::ScanAdded {
            id: 4,
            scan: scan(1.0),
            world_from_scan: p(1.0),
        })
        .unwrap();
        m.apply(ModelEvent::PoseRevised {
            id: 0,
            world_from_scan: p(0.5),
        })
        .unwrap();
        let listing = ScanListing::of_scan(&scan(2.0), 99, 3.0);
        m.apply(ModelEvent::ScanListed {
            id: 2,
            listing,
            world_from_scan: p(2.0),
        })
        .unwrap();
        assert_eq!(
            m.scans().iter().map(|s| s.id).collect::<Vec<_>>(),
            vec![0, 2, 4]
        );
        assert_eq!((m.len(), m.resident_len(), m.next_id()), (3, 2, 5));
        assert_eq!(
            m.apply(ModelEvent::PoseRevised {
                id: 9,
                world_from_scan: p(0.0)
            }),
            Err(ModelError::UnknownScan {
                id: 9,
                what: "pose revision"
            })
        );
        // Fetching a listed scan keeps its listing; evicting keeps it known.
        m.apply(ModelEvent::ScanAdded {
            id: 2,
            scan: scan(2.0),
            world_from_scan: p(2.0),
        })
        .unwrap();
        assert_eq!(m.get(2).unwrap().listing.encoded_bytes, 99);
        assert_eq!(m.resident_len(), 3);
        m.apply(ModelEvent::ScanEvicted { id: 4 }).unwrap();
        assert!(!m.get(4).unwrap().is_resident());
        assert_eq!(m.resident_len(), 2);
        m.apply(ModelEvent::ScanWithdrawn { id: 0 }).unwrap();
        assert!(m.get(0).is_none());
        assert_eq!((m.len(), m.resident_len()), (2, 1));

        let mut replica = Model::new();
        for e in m.snapshot() {
            replica.apply(e).unwrap();
        }
        assert_eq!((replica.len(), replica.resident_len()), (2, 1));
        assert_eq!(replica.get(2).unwrap().listing, m.get(2).unwrap().listing);
        assert!(!replica.get(4).unwrap().is_resident());
        assert_eq!(replica.get(4).unwrap().world_from_scan, p(1.0));
        assert_eq!(m.events_applied(), 7);
    }
}
