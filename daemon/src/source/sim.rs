//! The simulator as a source: a scene's texel frames (`sims::Simulator`) rendered
//! in-process on a few threads ahead of their time and sent at the trajectory's frame
//! rate (times `speed`), or as fast as they render, with each frame's true pose.
//!
//! Rendering a 640x480 frame takes tens of milliseconds per core, so at 10-30 Hz the
//! render threads may fall behind. What happens then is the session's explicit
//! policy (`late`): `skip` keeps the trajectory's clock (a frame still unrendered
//! when the next one is due is skipped, counted `late_skipped`, and rendering jumps
//! to the frame due now), `wait` sends every frame, late if need be (`late_frames`).
//! `prerender` renders every frame before the first is sent, so the pacing measures
//! the daemon alone.

use std::collections::BTreeMap;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use sims::{Scene, SimFrame, SimOptions, Simulator};
use texel::capture::PoseTopic;
use tokio_util::sync::CancellationToken;

use super::replay::Pace;
use super::{
    FrameSink, Source, SourceError, SourceEvent, SourceFuture, SourceMetrics, SourceState,
};
use crate::config::{LatePolicy, SimSetup};

/// The most memory `prerender` may hold.
const MAX_PRERENDER_BYTES: usize = 2 << 30;
/// The longest single wait, so shutdown is noticed promptly.
const WAIT_SLICE: Duration = Duration::from_millis(20);

/// Builds the simulator a setup describes; the error names the scene or option.
pub fn build_simulator(setup: &SimSetup) -> Result<Simulator, String> {
    let scene = Scene::load(&setup.scene).map_err(|e| e.to_string())?;
    let effects = match &setup.effects {
        Some(names) => Some(
            names
                .iter()
                .map(|n| sims::Effect::from_name_and_params(n, toml::Table::new()))
                .collect::<Result<Vec<_>, _>>()
                .map_err(|e| format!("{}: effects: {e}", setup.scene.display()))?,
        ),
        None => None,
    };
    let options = SimOptions {
        seed: setup.seed,
        effects,
        frames: setup.frames,
        lidar_size: setup.lidar_size,
        eo_size: setup.eo_size,
        ..SimOptions::default()
    };
    Simulator::with_options(scene, &options).map_err(|e| format!("{}: {e}", setup.scene.display()))
}

/// Renders and sends a simulation.
#[derive(Debug, Clone)]
pub struct SimSource {
    pub name: String,
    pub setup: SimSetup,
    pub pace: Pace,
    pub prerender: bool,
    /// 0 = one per core.
    pub render_threads: usize,
    pub late: LatePolicy,
    /// Send each frame's `/truth/pose`.
    pub truth: bool,
    /// Times the trajectory is walked (at least 1). Later walks send the first walk's
    /// renders again (kept in memory), timestamps continuing: a session of any
    /// length at the cost of one walk's rendering.
    pub loops: u32,
    /// Frames at or before this timestamp are not sent (nor rendered): a resumed
    /// session goes on after its recording ends.
    pub resume_after_ns: Option<u64>,
}

impl Source for SimSource {
    fn name(&self) -> &str {
        &self.name
    }

    fn kind(&self) -> &'static str {
        "sim"
    }

    fn run(self: Box<Self>, sink: FrameSink, shutdown: CancellationToken) -> SourceFuture {
        Box::pin(async move {
            let name = self.name.clone();
            super::on_blocking_thread(&name, "simulator thread", move || {
                self.simulate(&sink, &shutdown)
            })
            .await?
        })
    }
}

/// What the render threads and the sender share.
struct Shared {
    /// The next frame no thread has taken yet.
    next_to_render: usize,
    /// Frames below this are not wanted any more (skipped).
    skip_below: usize,
    /// The next frame the sender will send; renderers stay within `lookahead` of it.
    sending: usize,
    rendered: BTreeMap<usize, SimFrame>,
    /// A render failed: its message.
    failed: Option<String>,
    stop: bool,
}

struct Board {
    state: Mutex<Shared>,
    changed: Condvar,
}

impl Board {
    fn lock(&self) -> MutexGuard<'_, Shared> {
        self.state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn wait<'a>(&self, guard: MutexGuard<'a, Shared>) -> MutexGuard<'a, Shared> {
        match self.changed.wait_timeout(guard, WAIT_SLICE) {
            Ok((g, _)) => g,
            Err(p) => p.into_inner().0,
        }
    }
}

impl SimSource {
    fn fatal(&self, metrics: &SourceMetrics, message: String) -> SourceError {
        metrics.set_state(SourceState::Failed);
        metrics.report_error(message.clone());
        SourceError::Fatal {
            source_name: self.name.clone(),
            message,
        }
    }

    fn simulate(&self, sink: &FrameSink, shutdown: &CancellationToken) -> Result<(), SourceError> {
        let metrics = Arc::clone(sink.metrics());
        let sim = build_simulator(&self.setup).map_err(|e| self.fatal(&metrics, e))?;
        let frames = sim.frame_count();
        let m = sim.sensor_model();
        let frame_bytes = (m.eo.width as usize * m.eo.height as usize * 3)
            + (m.lidar.width as usize * m.lidar.height as usize * 8);
        // Several walks keep the first walk's renders, as prerendering does.
        let keep_all = self.prerender || self.loops > 1;
        if keep_all && frames.saturating_mul(frame_bytes) > MAX_PRERENDER_BYTES {
            return Err(self.fatal(
                &metrics,
                format!(
                    "prerendering {frames} frames would hold {} MiB (at most {} MiB)",
                    frames.saturating_mul(frame_bytes) >> 20,
                    MAX_PRERENDER_BYTES >> 20
                ),
            ));
        }
        if sink
            .blocking_send(SourceEvent::Sensor(Arc::new(m.clone())))
            .is_err()
        {
            return Ok(());
        }
        let threads = match self.render_threads {
            0 => std::thread::available_parallelism().map_or(2, |n| n.get()),
            n => n,
        };
        let lookahead = if keep_all { frames } else { threads + 2 };
        let board = Board {
            state: Mutex::new(Shared {
                next_to_render: 0,
                skip_below: 0,
                sending: 0,
                rendered: BTreeMap::new(),
                failed: None,
                stop: false,
            }),
            changed: Condvar::new(),
        };
        tracing::info!(
            source = %self.name,
            scene = %self.setup.scene.display(),
            frames,
            rate_hz = sim.frame_rate_hz(),
            pace = ?self.pace,
            threads,
            prerender = self.prerender,
            "simulator started"
        );
        let result = std::thread::scope(|scope| {
            for _ in 0..threads {
                scope.spawn(|| render_loop(&sim, &board, lookahead, &metrics));
            }
            let sent = self.send_loop(&sim, &board, sink, shutdown, &metrics);
            board.lock().stop = true;
            board.changed.notify_all();
            sent
        });
        match result {
            Ok(()) => {
                metrics.set_state(SourceState::Ended);
                tracing::info!(source = %self.name, "simulation ended");
                Ok(())
            }
            Err(message) => Err(self.fatal(&metrics, message)),
        }
    }

    /// Sends frames in order at the pace; `Err` when rendering failed.
    fn send_loop(
        &self,
        sim: &Simulator,
        board: &Board,
        sink: &FrameSink,
        shutdown: &CancellationToken,
        metrics: &SourceMetrics,
    ) -> Result<(), String> {
        let frames = sim.frame_count();
        let walks = self.loops.max(1) as usize;
        // Later walks repeat the first walk's renders: keep them.
        let keep = walks > 1;
        if self.prerender {
            let mut s = board.lock();
            while s.rendered.len() < frames && s.failed.is_none() {
                if shutdown.is_cancelled() {
                    return Ok(());
                }
                s = board.wait(s);
            }
        }
        metrics.set_state(SourceState::Running);
        let speed = match self.pace {
            Pace::Speed(s) => Some(s),
            Pace::Fast => None,
        };
        let walk_ns = walk_duration_ns(sim);
        // Frame `g` of the whole session is frame `g % frames` of walk `g / frames`.
        let timestamp = |g: usize| -> u64 {
            let walk = (g / frames.max(1)) as u64;
            sim.timestamp_ns(g % frames.max(1))
                .saturating_add(walk.saturating_mul(walk_ns))
        };
        let total = frames.saturating_mul(walks);
        // A resumed session starts after what its recording holds.
        let first = match self.resume_after_ns {
            Some(after) => (0..total).find(|&g| timestamp(g) > after).unwrap_or(total),
            None => 0,
        };
        if first > 0 && first < frames && !keep {
            let mut s = board.lock();
            s.skip_below = first;
            s.sending = first;
            drop(s);
            board.changed.notify_all();
        }
        let t0 = timestamp(first.min(total.saturating_sub(1)));
        let wall0 = Instant::now();
        metrics.set_clock_origin(t0, wall0);
        let due = |g: usize| -> Option<Instant> {
            let speed = speed?;
            let offset_s = timestamp(g).saturating_sub(t0) as f64 * 1e-9 / speed;
            Some(wall0 + Duration::from_secs_f64(offset_s.clamp(0.0, 1e9)))
        };
        let mut g = first;
        while g < total {
            if shutdown.is_cancelled() {
                return Ok(());
            }
            let i = g % frames;
            let walk = g / frames;
            // Wait until frame g is due.
            if let Some(at) = due(g) {
                while Instant::now() < at {
                    if shutdown.is_cancelled() {
                        return Ok(());
                    }
                    std::thread::sleep((at - Instant::now()).min(WAIT_SLICE));
                }
            }
            // Wait for it to be rendered: under `skip`, no longer than until the next
            // frame is due. A later walk has every render it will get.
            let give_up = match self.late {
                _ if walk > 0 => Some(Instant::now()),
                LatePolicy::Skip if g + 1 < total => due(g + 1),
                _ => None,
            };
            let frame = {
                let mut s = board.lock();
                loop {
                    if let Some(message) = s.failed.take() {
                        return Err(message);
                    }
                    let found = if keep {
                        s.rendered.get(&i).cloned()
                    } else {
                        s.rendered.remove(&i)
                    };
                    if let Some(f) = found {
                        break Some(f);
                    }
                    if shutdown.is_cancelled() {
                        return Ok(());
                    }
                    if give_up.is_some_and(|g| Instant::now() >= g) {
                        break None;
                    }
                    s = board.wait(s);
                }
            };
            let Some(mut frame) = frame else {
                if walk > 0 {
                    metrics.add_counter("late_skipped", 1);
                    g += 1;
                    continue;
                }
                // Skip to the frame due now; renderers follow.
                let now = Instant::now();
                let mut next = g + 1;
                while next + 1 < frames && due(next + 1).is_some_and(|d| d <= now) {
                    next += 1;
                }
                metrics.add_counter("late_skipped", (next - g) as u64);
                let mut s = board.lock();
                s.skip_below = next;
                s.sending = next;
                if !keep {
                    s.rendered.retain(|&k, _| k >= next);
                }
                drop(s);
                board.changed.notify_all();
                g = next;
                continue;
            };
            if let (Some(at), Some(period)) = (due(g), period(sim, speed))
                && Instant::now().saturating_duration_since(at) > period
            {
                metrics.add_counter("late_frames", 1);
            }
            if walk == 0 {
                let mut s = board.lock();
                s.sending = i + 1;
                drop(s);
                board.changed.notify_all();
            }
            let shift = timestamp(g) - sim.timestamp_ns(i);
            frame.timestamp_ns += shift;
            frame.pair.range.timestamp_ns += shift;
            frame.pair.eo.timestamp_ns += shift;
            if !self.send_frame(frame, sink) {
                return Ok(());
            }
            metrics.add_counter("frames_sent", 1);
            g += 1;
        }
        Ok(())
    }

    /// Sends one frame's truth, range and EO; false when the pipeline has stopped.
    fn send_frame(&self, frame: SimFrame, sink: &FrameSink) -> bool {
        // The truth first, so the pipeline knows it when the pair forms.
        if self.truth
            && sink
                .blocking_send(SourceEvent::Pose {
                    topic: PoseTopic::Truth,
                    timestamp_ns: frame.timestamp_ns,
                    world_from_eo: frame.world_from_eo,
                })
                .is_err()
        {
            return false;
        }
        sink.blocking_send(SourceEvent::Range(Arc::new(frame.pair.range)))
            .is_ok()
            && sink
                .blocking_send(SourceEvent::Eo(Arc::new(frame.pair.eo)))
                .is_ok()
    }
}

/// The time one walk of the trajectory takes, first frame to first frame of the
/// next walk: its span plus one frame period.
fn walk_duration_ns(sim: &Simulator) -> u64 {
    let frames = sim.frame_count();
    let span = sim
        .timestamp_ns(frames.saturating_sub(1))
        .saturating_sub(sim.timestamp_ns(0));
    let rate = sim.frame_rate_hz();
    let period_ns = if rate.is_finite() && rate > 0.0 {
        (1e9 / rate) as u64
    } else {
        0
    };
    span.saturating_add(period_ns.max(1))
}

/// One frame period on the wall clock at `speed`.
fn period(sim: &Simulator, speed: Option<f64>) -> Option<Duration> {
    let speed = speed?;
    let rate = sim.frame_rate_hz() * speed;
    (rate.is_finite() && rate > 0.0).then(|| Duration::from_secs_f64(1.0 / rate))
}

/// A render thread: takes the next wanted frame within the lookahead, renders it,
/// posts it.
fn render_loop(sim: &Simulator, board: &Board, lookahead: usize, metrics: &SourceMetrics) {
    let frames = sim.frame_count();
    loop {
        let index = {
            let mut s = board.lock();
            loop {
                if s.stop || s.failed.is_some() {
                    return;
                }
                let i = s.next_to_render.max(s.skip_below);
                if i >= frames {
                    return;
                }
                if i < s.sending + lookahead {
                    s.next_to_render = i + 1;
                    break i;
                }
                s = board.wait(s);
            }
        };
        let started = Instant::now();
        let rendered = sim.frame(index);
        let mut s = board.lock();
        match rendered {
            Ok(frame) => {
                metrics.add_counter("frames_rendered", 1);
                metrics.add_counter("render_ms_total", started.elapsed().as_millis() as u64);
                if index >= s.skip_below {
                    s.rendered.insert(index, frame);
                }
            }
            Err(e) => s.failed = Some(format!("frame {index}: {e}")),
        }
        drop(s);
        board.changed.notify_all();
    }
}
