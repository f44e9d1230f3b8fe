//! Decoding tiles off the render thread: a background thread takes encoded tiles from
//! a bounded queue, decodes them with `texel_lod::decode_tile` (bounded, never
//! panics) and hands the nodes back; the render thread uploads them. When the queue
//! is full a job is handed back to the caller, whose request stays wanted and is made
//! again next frame. A decode error names the tile; the other tiles still load.

use std::collections::BTreeMap;
use std::sync::mpsc::{Receiver, SyncSender, TryRecvError, TrySendError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use texel_lod::{LodNode, TileId, decode_tile};

use super::source::{EncodedTile, LoadError};

/// A tile decoded and ready to upload.
#[derive(Debug, Clone, PartialEq)]
pub struct DecodedTile {
    pub revision: u64,
    pub node: LodNode,
}

pub type LoadOutcome = Result<DecodedTile, LoadError>;

/// The decode thread and its queues.
pub struct TileLoader {
    jobs: Option<SyncSender<EncodedTile>>,
    results: Receiver<(TileId, LoadOutcome)>,
    worker: Option<JoinHandle<()>>,
    /// Submitted and not yet drained, with their revision.
    in_flight: BTreeMap<TileId, u64>,
}

fn decode(job: EncodedTile) -> (TileId, LoadOutcome) {
    let outcome = match decode_tile(&job.bytes) {
        Ok(node) if node.id == job.id => Ok(DecodedTile {
            revision: job.revision,
            node,
        }),
        Ok(node) => Err(LoadError {
            id: job.id,
            message: format!("the bytes hold tile {}", node.id.path()),
        }),
        Err(e) => Err(LoadError {
            id: job.id,
            message: format!("revision {}: {e}", job.revision),
        }),
    };
    (job.id, outcome)
}

impl TileLoader {
    /// Starts the decode thread with a queue of `queue_len` jobs (at least 1).
    pub fn spawn(queue_len: usize) -> std::io::Result<Self> {
        let (jobs, job_rx) = std::sync::mpsc::sync_channel::<EncodedTile>(queue_len.max(1));
        let (result_tx, results) = std::sync::mpsc::channel();
        let worker = std::thread::Builder::new()
            .name("tile decode".into())
            .spawn(move || {
                for job in job_rx {
                    if result_tx.send(decode(job)).is_err() {
                        break;
                    }
                }
            })?;
        Ok(Self {
            jobs: Some(jobs),
            results,
            worker: Some(worker),
            in_flight: BTreeMap::new(),
        })
    }

    /// Queues a job. A full queue (or a stopped thread) hands the job back: the
    /// caller drops it and asks again later.
    pub fn submit(&mut self, job: EncodedTile) -> Result<(), EncodedTile> {
        if self.in_flight.contains_key(&job.id) {
            // One decode of a tile at a time; the newer bytes come again later.
            return Err(job);
        }
        let Some(jobs) = &self.jobs else {
            return Err(job);
        };
        let (id, revision) = (job.id, job.revision);
        match jobs.try_send(job) {
            Ok(()) => {
                self.in_flight.insert(id, revision);
                Ok(())
            }
            Err(TrySendError::Full(job) | TrySendError::Disconnected(job)) => Err(job),
        }
    }

    /// Tiles submitted and not drained yet.
    pub fn in_flight(&self) -> usize {
        self.in_flight.len()
    }

    pub fn is_in_flight(&self, id: TileId) -> bool {
        self.in_flight.contains_key(&id)
    }

    /// What the thread has finished, without waiting.
    pub fn drain(&mut self) -> Vec<LoadOutcome> {
        let mut out = Vec::new();
        loop {
            match self.results.try_recv() {
                Ok((id, outcome)) => {
                    self.in_flight.remove(&id);
                    out.push(outcome);
                }
                Err(TryRecvError::Empty) => break,
                Err(TryRecvError::Disconnected) => {
                    out.extend(self.lost());
                    break;
                }
            }
        }
        out
    }

    /// Waits until nothing is in flight or `timeout` passed; returns what finished.
    pub fn wait(&mut self, timeout: Duration) -> Vec<LoadOutcome> {
        let deadline = Instant::now() + timeout;
        let mut out = Vec::new();
        while !self.in_flight.is_empty() {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                break;
            }
            match self.results.recv_timeout(left) {
                Ok((id, outcome)) => {
                    self.in_flight.remove(&id);
                    out.push(outcome);
                }
                Err(std::sync::mpsc::RecvTimeoutError::Timeout) => break,
                Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
                    out.extend(self.lost());
                    break;
                }
            }
        }
        out
    }

    /// Every tile in flight as an error: the thread stopped.
    fn lost(&mut self) -> Vec<LoadOutcome> {
        self.jobs = None;
        std::mem::take(&mut self.in_flight)
            .into_keys()
            .map(|id| {
                Err(LoadError {
                    id,
                    message: "the decode thread stopped".into(),
                })
            })
            .collect()
    }
}

impl Drop for TileLoader {
    fn drop(&mut self) {
        // Closing the queue ends the thread once it has finished its current job.
        self.jobs = None;
        if let Some(worker) = self.worker.take() {
            let _ = worker.join();
        }
    }
}
