//! `texel-sims serve-serial` (part of the binary): a scene's lidar frames as a virtual
//! TXL1 serial device on a new pseudo-terminal (its path printed on standard output)
//! or on a given tty, with fault injection.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result, bail};
use clap::Args;
use sims::serial::{
    DeviceEvent, SerialFaults, StopSignal, StreamEnd, VirtualLidar, VirtualLidarConfig, spawn_pty,
};
use sims::{Scene, SimOptions, Simulator};

#[derive(Args)]
pub struct ServeSerial {
    #[arg(long)]
    scene: PathBuf,
    /// Write to this serial device instead of a new pseudo-terminal.
    #[arg(long)]
    tty: Option<PathBuf>,
    /// Keep a symbolic link at this path to the current pseudo-terminal (it changes
    /// name when the device reappears after a disconnect).
    #[arg(long)]
    link: Option<PathBuf>,
    /// Seed of the simulation's noise.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Replace the scene's effects: a comma-separated list of names, or "none".
    #[arg(long)]
    effects: Option<String>,
    /// Repeat the trajectory (seq and timestamps keep counting); without it the
    /// device goes silent after the last frame and stays open.
    #[arg(long = "loop")]
    loop_trajectory: bool,
    /// Frames per second on the line (default: the trajectory's rate).
    #[arg(long)]
    rate_hz: Option<f64>,
    /// Micrometres per range count (1000 = millimetres).
    #[arg(long, default_value_t = 1000)]
    range_unit_um: u32,
    /// Send at most this many frames.
    #[arg(long)]
    max_frames: Option<u64>,
    /// Faults from a TOML file: the keys of the `faults` table of a session file
    /// (flags below override them).
    #[arg(long)]
    faults: Option<PathBuf>,
    /// A burst of garbage bytes before every N-th frame.
    #[arg(long)]
    garbage_every: Option<u32>,
    /// Bytes per garbage burst.
    #[arg(long)]
    garbage_bytes: Option<u32>,
    /// A wrong CRC on every N-th frame.
    #[arg(long)]
    crc_error_every: Option<u32>,
    /// Wrong CRCs on these frames (comma-separated seqs).
    #[arg(long, value_delimiter = ',')]
    crc_error_seqs: Vec<u32>,
    /// Drop every N-th frame (a sequence gap).
    #[arg(long)]
    drop_every: Option<u32>,
    /// Drop these frames (comma-separated seqs).
    #[arg(long, value_delimiter = ',')]
    drop_seqs: Vec<u32>,
    /// Go silent before this frame ...
    #[arg(long)]
    stall_at: Option<u32>,
    /// ... for this many seconds.
    #[arg(long)]
    stall_s: Option<f64>,
    /// Disappear before this frame ...
    #[arg(long)]
    disconnect_at: Option<u32>,
    /// ... and reappear after this many seconds (a new pseudo-terminal).
    #[arg(long)]
    reappear_after_s: Option<f64>,
}

impl ServeSerial {
    fn faults(&self) -> Result<SerialFaults> {
        let mut f = match &self.faults {
            Some(path) => {
                let text = std::fs::read_to_string(path)
                    .with_context(|| format!("cannot read {}", path.display()))?;
                toml::from_str(&text).with_context(|| format!("{}", path.display()))?
            }
            None => SerialFaults::default(),
        };
        macro_rules! set {
            ($flag:ident, $field:ident) => {
                if let Some(v) = self.$flag {
                    f.$field = v;
                }
            };
        }
        set!(garbage_every, garbage_every_frames);
        set!(garbage_bytes, garbage_bytes);
        set!(crc_error_every, crc_error_every_frames);
        set!(drop_every, drop_every_frames);
        set!(stall_s, stall_s);
        f.crc_error_seqs.extend(&self.crc_error_seqs);
        f.drop_seqs.extend(&self.drop_seqs);
        if self.stall_at.is_some() {
            f.stall_at_seq = self.stall_at;
        }
        if self.disconnect_at.is_some() {
            f.disconnect_at_seq = self.disconnect_at;
        }
        if self.reappear_after_s.is_some() {
            f.reappear_after_s = self.reappear_after_s;
        }
        Ok(f)
    }
}

fn say(text: &str) {
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{text}");
    let _ = out.flush();
}

pub fn serve_serial(args: &ServeSerial) -> Result<()> {
    let scene = Scene::load(&args.scene)?;
    let options = SimOptions {
        seed: args.seed,
        effects: args
            .effects
            .as_deref()
            .map(crate::parse_effects)
            .transpose()?,
        ..SimOptions::default()
    };
    let sim = Arc::new(Simulator::with_options(scene, &options)?);
    let config = VirtualLidarConfig {
        range_unit_um: args.range_unit_um,
        rate_hz: args.rate_hz,
        loop_trajectory: args.loop_trajectory,
        max_frames: args.max_frames,
        faults: args.faults()?,
    };
    let lidar = VirtualLidar::new(sim.clone(), config)?;
    eprintln!(
        "virtual TXL1 lidar: {}x{} at {:.1} Hz, {} frames{}, range unit {} um",
        sim.sensor_model().lidar.width,
        sim.sensor_model().lidar.height,
        args.rate_hz.unwrap_or(sim.frame_rate_hz()),
        sim.frame_count(),
        if args.loop_trajectory {
            ", looping"
        } else {
            ""
        },
        args.range_unit_um
    );
    match &args.tty {
        Some(tty) => serve_tty(lidar, tty),
        None => serve_pty(lidar, args.link.clone()),
    }
}

/// On a new pseudo-terminal: the slave's path on standard output (again on each
/// reappearance), events on standard error.
fn serve_pty(lidar: VirtualLidar, link: Option<PathBuf>) -> Result<()> {
    let device = spawn_pty(lidar, link)?;
    for event in device.events().iter() {
        match event {
            DeviceEvent::Ready { path } => {
                say(&path);
                eprintln!("waiting for a reader at {path}");
            }
            DeviceEvent::ReaderConnected => eprintln!("reader connected: streaming"),
            DeviceEvent::ReaderGone => eprintln!("reader closed the port: waiting for the next"),
            DeviceEvent::Stalling { seq, seconds } => {
                eprintln!("fault: stalling {seconds} s before frame {seq}")
            }
            DeviceEvent::Disconnected { seq } => {
                eprintln!("fault: disconnected before frame {seq}")
            }
            DeviceEvent::Reappeared { path } => {
                say(&path);
                eprintln!("reappeared at {path}");
            }
            DeviceEvent::Finished => {
                let log = device.log();
                eprintln!(
                    "finished: {} frames written ({} with a bad CRC), {} dropped, {} garbage \
                     bytes; the device stays open until interrupted",
                    log.frames_written, log.crc_errors, log.dropped, log.garbage_bytes
                );
            }
        }
    }
    // The event channel closes when the device thread ends: report why.
    device.stop()?;
    Ok(())
}

/// On a given tty (a real serial port, or one end of a pair made elsewhere).
fn serve_tty(mut lidar: VirtualLidar, path: &Path) -> Result<()> {
    let open = || {
        serialport::new(path.to_string_lossy(), 115_200)
            .timeout(std::time::Duration::from_secs(5))
            .open_native()
            .with_context(|| format!("cannot open {}", path.display()))
    };
    let stop = StopSignal::new();
    let mut port = open()?;
    eprintln!("writing to {}", path.display());
    loop {
        match lidar.run(&mut port, &stop)? {
            StreamEnd::Finished => {
                eprintln!("finished");
                return Ok(());
            }
            StreamEnd::Stopped => return Ok(()),
            StreamEnd::Disconnect { seq } => {
                drop(port);
                eprintln!("fault: disconnected before frame {seq}");
                let Some(delay) = lidar.config().faults.reappear_after_s else {
                    bail!("disconnected for good (no reappear_after_s)");
                };
                stop.sleep(std::time::Duration::from_secs_f64(delay));
                port = open()?;
                lidar.record_reappearance(&path.display().to_string());
                eprintln!("reopened {}", path.display());
            }
        }
    }
}
