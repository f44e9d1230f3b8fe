//! The gateway's merged model: per camera, its listed scans (under merged ids, with
//! their current poses), whether its listing has arrived (and what came live before
//! it), and a byte-bounded cache of scans' data; and the viewers' queues, to which
//! every change goes as a wire frame.

use std::collections::{BTreeMap, HashMap, VecDeque};

use bytes::Bytes;
use texel::model::{ScanId, ScanListing};
use texel::pose::Pose;
use texel::wire::zenoh_keys::{Topic, frame_head, split_frames, with_scan_id};
use texel::wire::{Limits, Message, decode_frame, kind};
use tokio::sync::mpsc;

use super::{MAX_CAMERAS, global_id};

/// Live changes held back per camera while its listing is asked for.
const MAX_HELD: usize = 4096;

/// What a caller sees of one camera.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CameraView {
    /// `texel/<site>/<camera>`.
    pub prefix: String,
    /// Its number: its scans' merged ids are `number << 24 | id`.
    pub number: usize,
    pub world_frame: Option<String>,
    pub alive: bool,
    pub listing_received: bool,
    pub scans: usize,
}

struct Camera {
    prefix: String,
    world_frame: Option<String>,
    alive: bool,
    listing_received: bool,
    /// Live changes before the listing arrived, in order.
    held: Vec<(Topic, Vec<u8>)>,
    /// Own id -> (listing, pose).
    scans: BTreeMap<ScanId, (ScanListing, Pose)>,
    /// The camera's listing order (coarse first), then new scans as they came; may
    /// name scans since withdrawn (skipped).
    order: Vec<ScanId>,
}

pub(crate) struct Cameras {
    cameras: Vec<Camera>,
    pub(crate) viewers: Vec<mpsc::Sender<Bytes>>,
    cache: HashMap<ScanId, Bytes>,
    cache_order: VecDeque<ScanId>,
    cache_bytes: usize,
    cache_budget: usize,
}

impl Cameras {
    pub fn new(cache_budget: usize) -> Self {
        Self {
            cameras: Vec::new(),
            viewers: Vec::new(),
            cache: HashMap::new(),
            cache_order: VecDeque::new(),
            cache_bytes: 0,
            cache_budget,
        }
    }

    pub fn views(&self) -> Vec<CameraView> {
        self.cameras
            .iter()
            .enumerate()
            .map(|(i, c)| CameraView {
                prefix: c.prefix.clone(),
                number: i + 1,
                world_frame: c.world_frame.clone(),
                alive: c.alive,
                listing_received: c.listing_received,
                scans: c.scans.len(),
            })
            .collect()
    }

    /// The camera's 1-based number, adding it if new; `None` past [`MAX_CAMERAS`].
    fn number(&mut self, prefix: &str) -> Option<usize> {
        if let Some(i) = self.cameras.iter().position(|c| c.prefix == prefix) {
            return Some(i + 1);
        }
        if self.cameras.len() >= MAX_CAMERAS {
            return None;
        }
        self.cameras.push(Camera {
            prefix: prefix.to_string(),
            world_frame: None,
            alive: false,
            listing_received: false,
            held: Vec::new(),
            scans: BTreeMap::new(),
            order: Vec::new(),
        });
        Some(self.cameras.len())
    }

    /// A camera's token appeared: (re)joined; its listing is to be asked for.
    pub fn joined(&mut self, prefix: &str) -> Option<usize> {
        let n = self.number(prefix)?;
        let c = &mut self.cameras[n - 1];
        c.alive = true;
        c.listing_received = false;
        Some(n)
    }

    /// A camera's token went away: its scans stay on screen (as a viewer of a daemon
    /// that stopped keeps its model) until it comes back with a new listing.
    pub fn left(&mut self, prefix: &str) {
        if let Some(c) = self.cameras.iter_mut().find(|c| c.prefix == prefix) {
            c.alive = false;
        }
    }

    pub fn set_info(&mut self, number: usize, info: &[u8]) {
        let frame = serde_json::from_slice::<serde_json::Value>(info)
            .ok()
            .and_then(|v| v.get("world_frame")?.as_str().map(str::to_string));
        if let Some(c) = self.cameras.get_mut(number - 1) {
            c.world_frame = frame;
        }
        let frames: Vec<(&str, &str)> = self
            .cameras
            .iter()
            .filter_map(|c| Some((c.prefix.as_str(), c.world_frame.as_deref()?)))
            .collect();
        if let Some((a, fa)) = frames.first()
            && let Some((b, fb)) = frames.iter().find(|(_, f)| f != fa)
        {
            tracing::warn!(
                "zenoh: {a} (frame {fa:?}) and {b} (frame {fb:?}) are in different world \
                 frames: each is drawn in its own, not aligned to the other"
            );
        }
    }

    /// A camera's listing (`ModelReset`, `ScanListed`s, `SnapshotComplete`): scans it
    /// no longer lists are withdrawn, the rest listed anew, then what was held back
    /// is applied.
    pub fn snapshot(&mut self, prefix: &str, payload: &[u8]) {
        let Some(n) = self.number(prefix) else { return };
        let Some(frames) = split_frames(payload) else {
            tracing::warn!("zenoh: {prefix}: a listing that is not whole frames");
            return;
        };
        let mut listed = BTreeMap::new();
        let mut order = Vec::new();
        for frame in frames {
            if let Ok(Some((
                Message::ScanListed {
                    id,
                    listing,
                    world_from_scan,
                },
                _,
            ))) = decode_frame(frame, &Limits::FROM_SERVER)
            {
                listed.insert(id, (listing, world_from_scan));
                order.push(id);
            }
        }
        let stale: Vec<ScanId> = self.cameras[n - 1]
            .scans
            .keys()
            .filter(|id| !listed.contains_key(id))
            .copied()
            .collect();
        for id in stale {
            self.withdraw(n, id);
        }
        self.cameras[n - 1].scans.clear();
        self.cameras[n - 1].order.clear();
        for id in order {
            if let Some(&(listing, pose)) = listed.get(&id) {
                self.list(n, id, listing, pose);
            }
        }
        let c = &mut self.cameras[n - 1];
        c.listing_received = true;
        for (topic, payload) in std::mem::take(&mut c.held) {
            self.apply(n, topic, &payload);
        }
    }

    /// A live change: applied, or held back until the camera's listing arrives.
    pub fn live(&mut self, prefix: &str, topic: Topic, payload: Vec<u8>) {
        let Some(n) = self.number(prefix) else { return };
        let c = &mut self.cameras[n - 1];
        if !c.listing_received && !matches!(topic, Topic::Status | Topic::Scan(_)) {
            if c.held.len() < MAX_HELD {
                c.held.push((topic, payload));
            }
            return;
        }
        self.apply(n, topic, &payload);
    }

    fn apply(&mut self, n: usize, topic: Topic, payload: &[u8]) {
        let decoded = decode_frame(payload, &Limits::FROM_SERVER)
            .ok()
            .flatten()
            .filter(|(_, used)| *used == payload.len())
            .map(|(m, _)| m);
        match (topic, decoded) {
            (
                Topic::Listing(_),
                Some(Message::ScanListed {
                    id,
                    listing,
                    world_from_scan,
                }),
            ) => self.list(n, id, listing, world_from_scan),
            (
                Topic::Pose(_),
                Some(Message::PoseRevised {
                    id,
                    world_from_scan,
                }),
            ) => {
                if let Some(entry) = self.cameras[n - 1].scans.get_mut(&id) {
                    entry.1 = world_from_scan;
                    if let Some(g) = global_id(n, id)
                        && let Some(frame) = with_scan_id(payload, g)
                    {
                        self.broadcast(Bytes::from(frame));
                    }
                }
            }
            (Topic::Withdrawn(_), Some(Message::ScanWithdrawn { id })) => self.withdraw(n, id),
            (Topic::Status, Some(Message::Status { .. })) => {
                self.broadcast(Bytes::copy_from_slice(payload));
            }
            (Topic::Scan(id), _) => self.keep_data(n, id, payload),
            _ => {}
        }
    }

    fn list(&mut self, n: usize, id: ScanId, listing: ScanListing, pose: Pose) {
        let Some(g) = global_id(n, id) else {
            tracing::warn!("zenoh: scan {id} of camera {n} is past the ids a gateway merges");
            return;
        };
        let c = &mut self.cameras[n - 1];
        if c.scans.insert(id, (listing, pose)).is_none() {
            c.order.push(id);
        }
        if let Ok(frame) = (Message::ScanListed {
            id: g,
            listing,
            world_from_scan: pose,
        })
        .encode()
        {
            self.broadcast(Bytes::from(frame));
        }
    }

    fn withdraw(&mut self, n: usize, id: ScanId) {
        let c = &mut self.cameras[n - 1];
        if c.scans.remove(&id).is_none() {
            return;
        }
        c.order.retain(|&x| x != id);
        let Some(g) = global_id(n, id) else { return };
        self.drop_data(g);
        if let Ok(frame) = (Message::ScanWithdrawn { id: g }).encode() {
            self.broadcast(Bytes::from(frame));
        }
    }

    /// Whether merged scan `g` is listed.
    pub fn is_listed(&self, g: ScanId) -> bool {
        let (n, id) = super::split_id(g);
        n >= 1
            && self
                .cameras
                .get(n - 1)
                .is_some_and(|c| c.scans.contains_key(&id))
    }

    /// The size of merged scan `g`'s data as its listing gives it (0 when unknown).
    pub fn encoded_bytes(&self, g: ScanId) -> u64 {
        let (n, id) = super::split_id(g);
        n.checked_sub(1)
            .and_then(|i| self.cameras.get(i))
            .and_then(|c| c.scans.get(&id))
            .map_or(0, |(listing, _)| listing.encoded_bytes)
    }

    /// The camera prefix and own id of merged scan `g`.
    pub fn source_of(&self, g: ScanId) -> Option<(String, ScanId)> {
        let (n, id) = super::split_id(g);
        let c = self.cameras.get(n.checked_sub(1)?)?;
        Some((c.prefix.clone(), id))
    }

    /// The frames of scan `(n, id)`'s data under its merged id; `None` when the
    /// payload is not a scan's data (a `ScanUnavailable` included).
    pub fn remap_data(n: usize, payload: &[u8]) -> Option<Vec<u8>> {
        let frames = split_frames(payload)?;
        let mut out = Vec::with_capacity(payload.len());
        for frame in frames {
            let (_, id) = frame_head(frame)?;
            out.extend(with_scan_id(frame, global_id(n, id?)?)?);
        }
        Some(out)
    }

    fn keep_data(&mut self, n: usize, id: ScanId, payload: &[u8]) {
        let Some(g) = global_id(n, id) else { return };
        if frame_head(
            split_frames(payload)
                .and_then(|f| f.first().copied())
                .unwrap_or(&[]),
        )
        .map(|(k, _)| k)
            != Some(kind::SCAN_ADDED)
        {
            return;
        }
        let Some(data) = Self::remap_data(n, payload) else {
            return;
        };
        self.drop_data(g);
        self.cache_bytes += data.len();
        self.cache.insert(g, Bytes::from(data));
        self.cache_order.push_back(g);
        while self.cache_bytes > self.cache_budget {
            let Some(old) = self.cache_order.pop_front() else {
                break;
            };
            if let Some(d) = self.cache.remove(&old) {
                self.cache_bytes -= d.len();
            }
        }
    }

    fn drop_data(&mut self, g: ScanId) {
        if let Some(d) = self.cache.remove(&g) {
            self.cache_bytes -= d.len();
            self.cache_order.retain(|&x| x != g);
        }
    }

    /// Scan `g`'s data when a camera put it and it is still kept.
    pub fn cached(&self, g: ScanId) -> Option<Bytes> {
        self.cache.get(&g).cloned()
    }

    /// What a viewer learns first: every listed scan of every camera, each camera's
    /// in its own order (coarse first), the cameras taken in turn so that every
    /// camera's coarse scans come early.
    pub fn snapshot_frames(&self) -> Vec<Bytes> {
        let count: u64 = self.cameras.iter().map(|c| c.scans.len() as u64).sum();
        let mut out = Vec::with_capacity(count as usize + 2);
        let mut push = |m: Message| {
            if let Ok(f) = m.encode() {
                out.push(Bytes::from(f));
            }
        };
        push(Message::ModelReset { scan_count: count });
        let longest = self
            .cameras
            .iter()
            .map(|c| c.order.len())
            .max()
            .unwrap_or(0);
        for k in 0..longest {
            for (i, c) in self.cameras.iter().enumerate() {
                let Some(&id) = c.order.get(k) else { continue };
                if let (Some(&(listing, pose)), Some(g)) = (c.scans.get(&id), global_id(i + 1, id))
                {
                    push(Message::ScanListed {
                        id: g,
                        listing,
                        world_from_scan: pose,
                    });
                }
            }
        }
        push(Message::SnapshotComplete { scan_count: count });
        out
    }

    /// Sends a frame to every viewer; one whose queue is full is dropped (its
    /// connection closes, and the viewer reconnects to a fresh snapshot).
    fn broadcast(&mut self, frame: Bytes) {
        self.viewers.retain(|tx| tx.try_send(frame.clone()).is_ok());
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use texel::pose::pose_from_parts;

    fn listing() -> ScanListing {
        ScanListing {
            timestamp_ns: 1,
            bounds_min_m: [0.0; 3],
            bounds_max_m: [1.0; 3],
            cop_m: [0.0; 3],
            priority: 0.5,
            encoded_bytes: 10,
        }
    }

    fn pose(x: f64) -> Pose {
        pose_from_parts([x, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]).unwrap()
    }

    fn frame(m: Message) -> Vec<u8> {
        m.encode().unwrap()
    }

    fn listed(id: ScanId, x: f64) -> Vec<u8> {
        frame(Message::ScanListed {
            id,
            listing: listing(),
            world_from_scan: pose(x),
        })
    }

    fn snapshot(ids: &[ScanId]) -> Vec<u8> {
        let mut out = frame(Message::ModelReset {
            scan_count: ids.len() as u64,
        });
        for &id in ids {
            out.extend(listed(id, id as f64));
        }
        out.extend(frame(Message::SnapshotComplete {
            scan_count: ids.len() as u64,
        }));
        out
    }

    /// Every frame a viewer subscribed now would be sent, decoded.
    fn drain(rx: &mut mpsc::Receiver<Bytes>) -> Vec<Message> {
        let mut out = Vec::new();
        while let Ok(f) = rx.try_recv() {
            out.push(decode_frame(&f, &Limits::FROM_SERVER).unwrap().unwrap().0);
        }
        out
    }

    #[test]
    fn live_changes_wait_for_the_listing_and_ids_are_merged() {
        let mut c = Cameras::new(1 << 20);
        let (tx, mut rx) = mpsc::channel(64);
        c.viewers.push(tx);
        assert_eq!(c.joined("texel/s/a"), Some(1));
        assert_eq!(c.joined("texel/s/b"), Some(2));
        // Camera b: a revision of scan 1 arrives before its listing, then scan 2.
        c.live(
            "texel/s/b",
            Topic::Pose(1),
            frame(Message::PoseRevised {
                id: 1,
                world_from_scan: pose(9.0),
            }),
        );
        c.live("texel/s/b", Topic::Listing(2), listed(2, 2.0));
        assert!(drain(&mut rx).is_empty(), "held back until the listing");
        c.snapshot("texel/s/b", &snapshot(&[1, 0]));
        let got = drain(&mut rx);
        let b = |i| global_id(2, i).unwrap();
        assert_eq!(
            got.iter()
                .map(|m| match m {
                    Message::ScanListed { id, .. } => ("listed", *id),
                    Message::PoseRevised { id, .. } => ("revised", *id),
                    other => panic!("{other:?}"),
                })
                .collect::<Vec<_>>(),
            vec![
                ("listed", b(1)),
                ("listed", b(0)),
                ("revised", b(1)),
                ("listed", b(2))
            ]
        );
        // Camera a lists its own scan 0: a different merged id.
        c.snapshot("texel/s/a", &snapshot(&[0]));
        assert!(c.is_listed(global_id(1, 0).unwrap()) && c.is_listed(b(0)));
        // A newcomer's snapshot: both cameras, coarse first in turn, current poses.
        let snap: Vec<Message> = c
            .snapshot_frames()
            .iter()
            .map(|f| decode_frame(f, &Limits::FROM_SERVER).unwrap().unwrap().0)
            .collect();
        assert_eq!(snap.first(), Some(&Message::ModelReset { scan_count: 4 }));
        let ids: Vec<ScanId> = snap
            .iter()
            .filter_map(|m| match m {
                Message::ScanListed { id, .. } => Some(*id),
                _ => None,
            })
            .collect();
        assert_eq!(ids, vec![global_id(1, 0).unwrap(), b(1), b(0), b(2)]);
        assert!(snap.contains(&Message::ScanListed {
            id: b(1),
            listing: listing(),
            world_from_scan: pose(9.0)
        }));
        // A new listing from camera b (after it restarted) withdraws what it lost.
        c.snapshot("texel/s/b", &snapshot(&[0]));
        let got = drain(&mut rx);
        assert!(
            got.contains(&Message::ScanWithdrawn { id: b(1) }),
            "{got:?}"
        );
        assert!(
            got.contains(&Message::ScanWithdrawn { id: b(2) }),
            "{got:?}"
        );
        assert!(!c.is_listed(b(1)) && c.is_listed(b(0)));
    }

    #[test]
    fn scan_data_are_remapped_and_kept_within_the_budget() {
        let data = |id| {
            let mut f = frame(Message::ScanWithdrawn { id });
            // A ScanAdded-shaped frame: the kind byte and the id are all the cache reads.
            f[crate::zenoh_gateway::tests_support::KIND_AT] = kind::SCAN_ADDED;
            f
        };
        let mut c = Cameras::new(2 * data(0).len());
        c.joined("texel/s/a");
        c.snapshot("texel/s/a", &snapshot(&[0, 1, 2]));
        for id in 0..3 {
            c.live("texel/s/a", Topic::Scan(id), data(id));
        }
        let g = |i| global_id(1, i).unwrap();
        assert!(c.cached(g(0)).is_none(), "the oldest left the budget");
        let kept = c.cached(g(2)).unwrap();
        assert_eq!(frame_head(&kept), Some((kind::SCAN_ADDED, Some(g(2)))));
        // Not a scan's data: not kept.
        c.live(
            "texel/s/a",
            Topic::Scan(1),
            frame(Message::ScanUnavailable {
                id: 1,
                reason: "x".into(),
            }),
        );
        assert_eq!(c.cached(g(1)).map(|f| f.len()), Some(data(1).len()));
        // A ScanUnavailable answer is remapped all the same.
        let answer = frame(Message::ScanUnavailable {
            id: 7,
            reason: "gone".into(),
        });
        let remapped = Cameras::remap_data(3, &answer).unwrap();
        assert_eq!(
            frame_head(&remapped),
            Some((kind::SCAN_UNAVAILABLE, Some(global_id(3, 7).unwrap())))
        );
    }
}
