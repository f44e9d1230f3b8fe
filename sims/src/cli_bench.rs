//! `texel-sims bench`: texel frames per second with no effects (the baseline), each
//! effect alone, the scene's default effects and all effects, timed in interleaved
//! rounds so that a burst of load on a shared machine spoils one round, not one
//! configuration.

use std::path::Path;
use std::time::Instant;

use anyhow::Result;
use sims::effects::effect_docs;
use sims::{Effect, Scene, SimOptions, Simulator};

/// CPU time (user + system) of this process in seconds, from `/proc/self/stat`
/// (Linux clock ticks, 100 per second); `None` where that is not readable.
fn process_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let after = stat.rsplit_once(')')?.1;
    let fields: Vec<&str> = after.split_whitespace().collect();
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    Some((utime + stime) / 100.0)
}

/// One configuration under test and its best round so far.
struct Config {
    name: String,
    sim: Simulator,
    /// Next frame index to render (cycling over the trajectory).
    next: usize,
    best_fps: f64,
    best_cpu_s: Option<f64>,
}

impl Config {
    fn new(name: String, scene: &Scene, effects: Option<Vec<Effect>>) -> Result<Self> {
        let sim = Simulator::with_options(
            scene.clone(),
            &SimOptions {
                effects,
                ..SimOptions::default()
            },
        )?;
        // One warm-up frame (page faults, thread pool start).
        let _ = sim.frame(0)?;
        Ok(Self {
            name,
            sim,
            next: 0,
            best_fps: 0.0,
            best_cpu_s: None,
        })
    }

    /// Renders `frames` frames and keeps the round's figures if it is the fastest.
    fn round(&mut self, frames: usize) -> Result<()> {
        let start = Instant::now();
        let cpu_start = process_cpu_seconds();
        for _ in 0..frames {
            let frame = self.sim.frame(self.next % self.sim.frame_count().max(1))?;
            std::hint::black_box(&frame);
            self.next += 1;
        }
        let fps = frames as f64 / start.elapsed().as_secs_f64().max(1e-9);
        if fps > self.best_fps {
            self.best_fps = fps;
            self.best_cpu_s = match (cpu_start, process_cpu_seconds()) {
                (Some(a), Some(b)) => Some((b - a) / frames as f64),
                _ => None,
            };
        }
        Ok(())
    }

    fn cpu_text(&self) -> String {
        self.best_cpu_s
            .map_or_else(String::new, |c| format!("  {:>6.1} ms CPU/frame", c * 1e3))
    }
}

pub fn bench(scene_path: &Path, frames: usize, rounds: usize) -> Result<()> {
    let rounds = rounds.max(1);
    let scene = Scene::load(scene_path)?;
    let per_round = frames.div_ceil(rounds).max(1);
    let (lidar, eo) = (&scene.sensor().lidar, &scene.sensor().eo);
    println!(
        "scene {}: lidar {}x{}, EO {}x{}, {} threads; {rounds} interleaved rounds of \
         {per_round} frames per configuration, the fastest round shown",
        scene.name,
        lidar.width,
        lidar.height,
        eo.width,
        eo.height,
        rayon::current_num_threads()
    );
    println!(
        "(wall-clock frames/s depend on the machine's load; CPU ms/frame include rayon's idle spinning)"
    );
    // Effects only Mitsuba simulates are timed by `--mitsuba`.
    let builtin: Vec<&str> = effect_docs()
        .iter()
        .filter(|d| !d.needs_mitsuba)
        .map(|d| d.name)
        .collect();
    let with_defaults = |names: &[&str]| -> Result<Vec<Effect>> {
        names
            .iter()
            .map(|n| Effect::with_defaults(n).map_err(anyhow::Error::msg))
            .collect()
    };
    let mut configs = vec![Config::new(
        "no effects".to_string(),
        &scene,
        Some(Vec::new()),
    )?];
    for name in &builtin {
        configs.push(Config::new(
            name.to_string(),
            &scene,
            Some(with_defaults(&[name])?),
        )?);
    }
    let default_names = scene.effect_set().names().join(", ");
    configs.push(Config::new(
        format!("scene default ({default_names})"),
        &scene,
        None,
    )?);
    configs.push(Config::new(
        "all effects".to_string(),
        &scene,
        Some(with_defaults(&builtin)?),
    )?);
    // Each round starts one configuration further on, so none always runs first
    // (after the previous round's heaviest) or last.
    let count = configs.len();
    for round in 0..rounds {
        for k in 0..count {
            if let Some(config) = configs.get_mut((round + k) % count) {
                config.round(per_round)?;
            }
        }
    }
    let baseline = configs.first().map_or(1.0, |c| c.best_fps);
    for (i, c) in configs.iter().enumerate() {
        let ratio = if i == 0 {
            "(baseline)     ".to_string()
        } else {
            format!("{:>5.2}x baseline time", baseline / c.best_fps.max(1e-9))
        };
        println!(
            "{:<28} {:>8.1} frames/s  {ratio}{}",
            c.name,
            c.best_fps,
            c.cpu_text()
        );
    }
    Ok(())
}
