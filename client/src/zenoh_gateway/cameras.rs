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
            }
        }
        let old = std::mem::take(&mut self.cameras[n - 1].scans);
        for id in old.keys().filter(|id| !listed.contains_key(id)) {
            self.withdraw(n, *id);
        }
        for (id, (listing, pose)) in listed {
            self.list(n, id, listing, pose);
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
        self.cameras[n - 1].scans.insert(id, (listing, pose));
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
        if self.cameras[n - 1].scans.remove(&id).is_none() {
            return;
        }
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

    /// What a viewer learns first: every listed scan of every camera.
    pub fn snapshot_frames(&self) -> Vec<Bytes> {
        let count: u64 = self.cameras.iter().map(|c| c.scans.len() as u64).sum();
        let mut out = Vec::with_capacity(count as usize + 2);
        let mut push = |m: Message| {
            if let Ok(f) = m.encode() {
                out.push(Bytes::from(f));
            }
        };
        push(Message::ModelReset { scan_count: count });
        for (i, c) in self.cameras.iter().enumerate() {
            for (&id, &(listing, pose)) in &c.scans {
                if let Some(g) = global_id(i + 1, id) {
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
