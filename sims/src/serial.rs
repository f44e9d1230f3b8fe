//! The virtual TXL1 lidar: a simulation's range frames as the byte stream of a serial
//! lidar (TXL1 as [`texel::txl1`] defines it; the device's use is in
//! `docs/simulator.md`, virtual serial lidar), paced at the trajectory's rate, with
//! injected faults (garbage between frames, CRC errors, dropped frames, a stall, a
//! disconnect), written to any [`Write`] ([`VirtualLidar::run`]) or to a
//! pseudo-terminal that a reader opens like a real port ([`spawn_pty`]).
//!
//! Frame `seq` carries the lidar frame of [`Simulator::frame`]`(seq mod n)` (n = the
//! simulation's frame count); when the trajectory loops, seq and timestamps keep
//! counting (lap `k` is shifted by `k` trajectory periods), so a reader pairs each
//! lidar frame with the EO frame of [`sim_frame_for_seq`]. Every fault is recorded in
//! an [`InjectionLog`], so a reader's counters can be checked against what was done.

mod pty;

use std::io::Write;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use texel::txl1::Txl1Frame;
use thiserror::Error;

use crate::rng::mix64;
use crate::simulator::{SimError, SimFrame, Simulator};

pub use pty::{DeviceEvent, PtyDevice, spawn_pty};

/// Entries kept per list of the injection log (counts keep going past it).
pub const MAX_LOGGED: usize = 65_536;
/// Longest stall or reappearance delay, seconds.
const MAX_DELAY_S: f64 = 3600.0;

/// Faults to inject. "Every N frames" applies to the frames whose `seq + 1` is a
/// multiple of N (N = 10: seqs 9, 19, ...); 0 = never. A frame both dropped and
/// corrupted is dropped.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SerialFaults {
    /// A burst of `garbage_bytes` random bytes before every N-th frame. The bytes are
    /// never `T` (0x54), so they cannot start a false magic: a receiver skips exactly
    /// them.
    pub garbage_every_frames: u32,
    pub garbage_bytes: u32,
    /// The CRC of every N-th frame is wrong (its last byte inverted).
    pub crc_error_every_frames: u32,
    /// And of these frames.
    pub crc_error_seqs: Vec<u32>,
    /// Every N-th frame is not sent (a sequence gap).
    pub drop_every_frames: u32,
    /// And these frames.
    pub drop_seqs: Vec<u32>,
    /// Before sending this frame, the line goes silent for `stall_s` seconds.
    pub stall_at_seq: Option<u32>,
    pub stall_s: f64,
    /// Before sending this frame, the device disappears (a pseudo-terminal closes;
    /// a given tty is closed).
    pub disconnect_at_seq: Option<u32>,
    /// ... and reappears after this many seconds (a new pseudo-terminal, under a new
    /// name; a given tty is reopened), continuing with the same frame; absent: it
    /// stays gone.
    pub reappear_after_s: Option<f64>,
    /// Seed of the garbage bytes.
    pub seed: u64,
}

impl Default for SerialFaults {
    fn default() -> Self {
        Self {
            garbage_every_frames: 0,
            garbage_bytes: 64,
            crc_error_every_frames: 0,
            crc_error_seqs: Vec::new(),
            drop_every_frames: 0,
            drop_seqs: Vec::new(),
            stall_at_seq: None,
            stall_s: 2.0,
            disconnect_at_seq: None,
            reappear_after_s: None,
            seed: 0,
        }
    }
}

/// The virtual device's settings; the daemon's session file embeds this table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct VirtualLidarConfig {
    /// Micrometres per range count on the wire (1000 = millimetres).
    pub range_unit_um: u32,
    /// Frames per second on the line (default: the trajectory's rate). Timestamps are
    /// always the trajectory's.
    pub rate_hz: Option<f64>,
    /// Repeat the trajectory (seq and timestamps keep counting); otherwise the device
    /// goes silent after the last frame and stays open.
    pub loop_trajectory: bool,
    /// Send at most this many frames (dropped ones included).
    pub max_frames: Option<u64>,
    pub faults: SerialFaults,
}

impl Default for VirtualLidarConfig {
    fn default() -> Self {
        Self {
            range_unit_um: 1000,
            rate_hz: None,
            loop_trajectory: false,
            max_frames: None,
            faults: SerialFaults::default(),
        }
    }
}

impl VirtualLidarConfig {
    /// Checks the values; the message names the setting.
    pub fn validate(&self) -> Result<(), SerialError> {
        let bad = |m: String| Err(SerialError::Config(m));
        if self.range_unit_um == 0 {
            return bad("range_unit_um must be > 0".into());
        }
        if let Some(r) = self.rate_hz
            && !(r.is_finite() && r > 0.0 && r <= 10_000.0)
        {
            return bad(format!("rate_hz = {r} is outside (0, 10000]"));
        }
        let f = &self.faults;
        if f.garbage_bytes > 1 << 20 {
            return bad(format!(
                "faults.garbage_bytes = {} exceeds 1 MiB",
                f.garbage_bytes
            ));
        }
        for (name, v) in [
            ("faults.stall_s", Some(f.stall_s)),
            ("faults.reappear_after_s", f.reappear_after_s),
        ] {
            if let Some(v) = v
                && !(v.is_finite() && (0.0..=MAX_DELAY_S).contains(&v))
            {
                return bad(format!("{name} = {v} is outside [0, {MAX_DELAY_S}]"));
            }
        }
        if f.crc_error_seqs.len() > MAX_LOGGED || f.drop_seqs.len() > MAX_LOGGED {
            return bad(format!("at most {MAX_LOGGED} listed seqs per fault"));
        }
        Ok(())
    }
}

#[derive(Debug, Error)]
pub enum SerialError {
    #[error("virtual lidar: {0}")]
    Config(String),
    #[error(transparent)]
    Sim(#[from] SimError),
    #[error("frame {seq}: {width}x{height} does not fit a TXL1 frame")]
    Frame { seq: u32, width: u32, height: u32 },
    /// Writing failed (a reader that went away shows as `BrokenPipe`).
    #[error("writing to the serial line: {0}")]
    Write(#[source] std::io::Error),
    #[error("serial device {path}: {message}")]
    Device { path: String, message: String },
}

/// A stall the device made.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StallRecord {
    /// The frame sent after the silence.
    pub before_seq: u32,
    /// Seconds since the device started.
    pub at_s: f64,
    pub duration_s: f64,
}

/// A disconnection the device made.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DisconnectRecord {
    /// The first frame not sent before it.
    pub before_seq: u32,
    /// Seconds since the device started.
    pub at_s: f64,
    /// The device path it came back under, and when.
    pub reappeared_as: Option<String>,
    pub reappeared_at_s: Option<f64>,
}

/// Exactly what the device did to the line.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct InjectionLog {
    /// Frames put on the line whole, including those with a bad CRC.
    pub frames_written: u64,
    /// Every byte written (frames, garbage).
    pub bytes_written: u64,
    pub last_seq_written: Option<u32>,
    /// Garbage bytes written between frames, and the frames they preceded.
    pub garbage_bytes: u64,
    pub garbage_before_seqs: Vec<u32>,
    /// Frames written with a wrong CRC.
    pub crc_errors: u64,
    pub crc_error_seqs: Vec<u32>,
    /// Frames not sent (sequence gaps).
    pub dropped: u64,
    pub dropped_seqs: Vec<u32>,
    /// Frames cut off because the reader closed the port while they were written.
    pub undelivered_seqs: Vec<u32>,
    /// Times a reader closed the port.
    pub reader_disconnects: u64,
    pub stalls: Vec<StallRecord>,
    pub disconnects: Vec<DisconnectRecord>,
}

fn push_capped(list: &mut Vec<u32>, v: u32) {
    if list.len() < MAX_LOGGED {
        list.push(v);
    }
}

/// A stop request shared with the thread that runs a device; also its interruptible
/// sleep.
#[derive(Debug, Clone, Default)]
pub struct StopSignal(Arc<(Mutex<bool>, Condvar)>);

impl StopSignal {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn stop(&self) {
        let (lock, cvar) = &*self.0;
        if let Ok(mut s) = lock.lock() {
            *s = true;
        }
        cvar.notify_all();
    }

    pub fn is_stopped(&self) -> bool {
        self.0.0.lock().map_or(true, |s| *s)
    }

    /// Sleeps until `deadline` or a stop; true when stopped.
    pub fn sleep_until(&self, deadline: Instant) -> bool {
        let (lock, cvar) = &*self.0;
        let Ok(mut stopped) = lock.lock() else {
            return true;
        };
        while !*stopped {
            let now = Instant::now();
            if now >= deadline {
                return false;
            }
            match cvar.wait_timeout(stopped, deadline - now) {
                Ok((s, _)) => stopped = s,
                Err(_) => return true,
            }
        }
        true
    }

    pub fn sleep(&self, d: Duration) -> bool {
        self.sleep_until(Instant::now() + d)
    }
}

/// How [`VirtualLidar::run`] ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StreamEnd {
    /// The last frame was sent (trajectory end, or `max_frames`).
    Finished,
    /// [`StopSignal::stop`] was called.
    Stopped,
    /// The disconnect fault fired before frame `seq`: the caller closes the line
    /// (and reopens it for the next `run`, which continues with `seq`).
    Disconnect { seq: u32 },
}

/// The index into the simulation and the timestamp of frame `seq`: lap `k =
/// seq / n` of the trajectory is shifted by `k` periods of `n` frames.
pub fn frame_of_seq(sim: &Simulator, seq: u32) -> (usize, u64) {
    let n = sim.frame_count().max(1);
    let index = seq as usize % n;
    let lap = (seq as usize / n) as u64;
    let period_ns = (n as f64 / sim.frame_rate_hz() * 1e9).round() as u64;
    (
        index,
        sim.timestamp_ns(index)
            .saturating_add(lap.saturating_mul(period_ns)),
    )
}

/// The texel frame whose lidar half is frame `seq` of the virtual device: the
/// simulation's frame `seq mod n`, with the seq and looped timestamp, so the EO frame
/// pairs with the lidar frame read from the line.
pub fn sim_frame_for_seq(sim: &Simulator, seq: u32) -> Result<SimFrame, SimError> {
    let (index, timestamp_ns) = frame_of_seq(sim, seq);
    let mut frame = sim.frame(index)?;
    frame.timestamp_ns = timestamp_ns;
    frame.pair.range.timestamp_ns = timestamp_ns;
    frame.pair.range.seq = seq;
    frame.pair.eo.timestamp_ns = timestamp_ns;
    Ok(frame)
}

fn every(n: u32, seq: u32) -> bool {
    n > 0 && (u64::from(seq) + 1).is_multiple_of(u64::from(n))
}

/// The virtual lidar: renders each frame's range image and writes it as TXL1, with
/// faults.
pub struct VirtualLidar {
    sim: Arc<Simulator>,
    config: VirtualLidarConfig,
    log: Arc<Mutex<InjectionLog>>,
    started: Instant,
    next_seq: u32,
    stalled: bool,
    disconnected: bool,
    /// Where stalls are announced (set by [`spawn_pty`]).
    events: Option<std::sync::mpsc::SyncSender<DeviceEvent>>,
}

impl VirtualLidar {
    pub fn new(sim: Arc<Simulator>, config: VirtualLidarConfig) -> Result<Self, SerialError> {
        config.validate()?;
        let lidar = &sim.sensor_model().lidar;
        if lidar.width > u32::from(texel::txl1::MAX_SIDE)
            || lidar.height > u32::from(texel::txl1::MAX_SIDE)
        {
            return Err(SerialError::Frame {
                seq: 0,
                width: lidar.width,
                height: lidar.height,
            });
        }
        Ok(Self {
            sim,
            config,
            log: Arc::new(Mutex::new(InjectionLog::default())),
            started: Instant::now(),
            next_seq: 0,
            stalled: false,
            disconnected: false,
            events: None,
        })
    }

    pub fn config(&self) -> &VirtualLidarConfig {
        &self.config
    }

    pub fn simulator(&self) -> &Arc<Simulator> {
        &self.sim
    }

    /// A copy of the injection log so far.
    pub fn log(&self) -> InjectionLog {
        self.log.lock().map(|l| l.clone()).unwrap_or_default()
    }

    /// The live log (another thread may watch it while the device runs).
    pub fn log_handle(&self) -> Arc<Mutex<InjectionLog>> {
        self.log.clone()
    }

    /// The next frame to send.
    pub fn next_seq(&self) -> u32 {
        self.next_seq
    }

    /// Frame `seq` as it goes on the wire without faults.
    pub fn wire_frame(&self, seq: u32) -> Result<Txl1Frame, SerialError> {
        let (index, timestamp_ns) = frame_of_seq(&self.sim, seq);
        let pose = self.sim.true_pose(index);
        let mut range = self.sim.range_at(&pose, index as u64, timestamp_ns);
        if let Some(reason) = self.sim.backend_failure() {
            return Err(SerialError::Sim(SimError::Backend {
                backend: self.sim.backend_name(),
                reason,
            }));
        }
        range.seq = seq;
        Txl1Frame::from_range_frame(&range, self.config.range_unit_um).ok_or(SerialError::Frame {
            seq,
            width: range.width,
            height: range.height,
        })
    }

    fn with_log(&self, f: impl FnOnce(&mut InjectionLog)) {
        if let Ok(mut log) = self.log.lock() {
            f(&mut log);
        }
    }

    fn seconds(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }

    /// Records that the line came back under `path` (pseudo-terminals change name).
    pub fn record_reappearance(&self, path: &str) {
        let at = self.seconds();
        self.with_log(|l| {
            if let Some(d) = l.disconnects.last_mut() {
                d.reappeared_as = Some(path.to_string());
                d.reappeared_at_s = Some(at);
            }
        });
    }

    /// Records that the reader closed the port while frame `seq` was written.
    pub fn record_reader_gone(&self, seq: u32) {
        self.with_log(|l| {
            l.reader_disconnects += 1;
            push_capped(&mut l.undelivered_seqs, seq);
        });
    }

    /// Writes frames to `out` at the configured rate until the stream ends, a stop is
    /// requested, or the disconnect fault fires. A later call continues with the next
    /// frame. A write error ends the call; the frame being written then counts as
    /// sent (the caller records it with [`Self::record_reader_gone`] if the reader
    /// went away).
    pub fn run(
        &mut self,
        out: &mut dyn Write,
        stop: &StopSignal,
    ) -> Result<StreamEnd, SerialError> {
        let rate = self
            .config
            .rate_hz
            .unwrap_or_else(|| self.sim.frame_rate_hz());
        let interval = Duration::from_secs_f64(1.0 / rate);
        let mut anchor = Instant::now();
        let mut slot: u32 = 0;
        // When the last bytes went out: a disconnect waits one interval after them
        // even when rendering has fallen behind the time slots, so the reader has
        // had the time the slot promises to read the frame before it.
        let mut last_write = Instant::now();
        let total = self.sim.frame_count() as u64;
        loop {
            if stop.is_stopped() {
                return Ok(StreamEnd::Stopped);
            }
            let seq = self.next_seq;
            let sent = u64::from(seq);
            if self.config.max_frames.is_some_and(|m| sent >= m)
                || (!self.config.loop_trajectory && sent >= total)
                || (sent > u64::from(u32::MAX) - 1)
            {
                return Ok(StreamEnd::Finished);
            }
            let faults = &self.config.faults;
            let disconnect = faults.disconnect_at_seq == Some(seq) && !self.disconnected;
            let stall = faults.stall_at_seq == Some(seq) && !self.stalled;
            let dropped = every(faults.drop_every_frames, seq) || faults.drop_seqs.contains(&seq);
            let corrupt = !dropped
                && (every(faults.crc_error_every_frames, seq)
                    || faults.crc_error_seqs.contains(&seq));
            let garbage = every(faults.garbage_every_frames, seq) && faults.garbage_bytes > 0;
            // Rendered ahead of the frame's time slot.
            let bytes = if dropped || disconnect {
                None
            } else {
                let mut bytes = self.wire_frame(seq)?.encode();
                if corrupt && let Some(last) = bytes.last_mut() {
                    *last ^= 0xFF;
                }
                Some(bytes)
            };
            if stop.sleep_until(anchor + interval * slot) {
                return Ok(StreamEnd::Stopped);
            }
            slot = slot.saturating_add(1);
            // Faults happen in the frame's time slot, so the frame before them has had
            // one frame interval to reach the reader.
            if disconnect {
                if stop.sleep_until(last_write + interval) {
                    return Ok(StreamEnd::Stopped);
                }
                self.disconnected = true;
                let at_s = self.seconds();
                self.with_log(|l| {
                    l.disconnects.push(DisconnectRecord {
                        before_seq: seq,
                        at_s,
                        reappeared_as: None,
                        reappeared_at_s: None,
                    })
                });
                return Ok(StreamEnd::Disconnect { seq });
            }
            if stall {
                self.stalled = true;
                let (at_s, start) = (self.seconds(), Instant::now());
                if let Some(events) = &self.events {
                    let _ = events.try_send(DeviceEvent::Stalling {
                        seq,
                        seconds: self.config.faults.stall_s,
                    });
                }
                let stopped = stop.sleep(Duration::from_secs_f64(self.config.faults.stall_s));
                let duration_s = start.elapsed().as_secs_f64();
                self.with_log(|l| {
                    l.stalls.push(StallRecord {
                        before_seq: seq,
                        at_s,
                        duration_s,
                    })
                });
                if stopped {
                    return Ok(StreamEnd::Stopped);
                }
                // The device resumes its rhythm after the silence, with this frame.
                anchor = Instant::now();
                slot = 1;
            }
            self.next_seq = seq.wrapping_add(1);
            let faults = &self.config.faults;
            if garbage {
                let junk = garbage_bytes(faults.seed, seq, faults.garbage_bytes);
                out.write_all(&junk).map_err(SerialError::Write)?;
                last_write = Instant::now();
                self.with_log(|l| {
                    l.garbage_bytes += junk.len() as u64;
                    l.bytes_written += junk.len() as u64;
                    push_capped(&mut l.garbage_before_seqs, seq);
                });
            }
            let Some(bytes) = bytes else {
                self.with_log(|l| {
                    l.dropped += 1;
                    push_capped(&mut l.dropped_seqs, seq);
                });
                continue;
            };
            out.write_all(&bytes)
                .and_then(|()| out.flush())
                .map_err(SerialError::Write)?;
            last_write = Instant::now();
            self.with_log(|l| {
                l.frames_written += 1;
                l.bytes_written += bytes.len() as u64;
                l.last_seq_written = Some(seq);
                if corrupt {
                    l.crc_errors += 1;
                    push_capped(&mut l.crc_error_seqs, seq);
                }
            });
        }
    }
}

/// `n` bytes of line noise for the burst before frame `seq`, never `T` (0x54).
fn garbage_bytes(seed: u64, seq: u32, n: u32) -> Vec<u8> {
    (0..u64::from(n))
        .map(|i| {
            let b = (mix64(seed ^ mix64(u64::from(seq) << 32 | i)) >> 56) as u8;
            if b == texel::txl1::MAGIC[0] {
                b ^ 0x80
            } else {
                b
            }
        })
        .collect()
}
