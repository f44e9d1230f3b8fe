//! The serial lidar source: TXL1 range frames (the serial lidar protocol, decoded by
//! `texel::txl1`; docs/daemon.md) from a serial device. Resynchronises, counts every
//! skipped byte, CRC error and lost sequence number, decodes in slices of bounded work
//! with yields between them (so hostile bytes cannot starve shutdown or stall
//! detection), and survives the device going silent or away: it is reported and
//! reopened with backoff, possibly under another name when the path is a glob
//! (`/dev/ttyACM*`), keeping every frame already received.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use texel::txl1::{Txl1Counters, Txl1Decoder, Txl1Step};
use tokio::io::AsyncReadExt;
use tokio_serial::SerialStream;
use tokio_util::sync::CancellationToken;

use super::{
    FrameSink, Source, SourceError, SourceEvent, SourceFuture, SourceMetrics, SourceState,
    sleep_or_shutdown,
};

/// The serial source's settings.
#[derive(Debug, Clone)]
pub struct SerialSource {
    pub name: String,
    /// A device path, or a glob pattern whose first match (in sorted order) is used.
    pub path: String,
    pub baud: u32,
    /// A line silent this long is reported and reopened.
    pub stall_timeout: Duration,
    pub backoff_min: Duration,
    pub backoff_max: Duration,
}

/// Decoding work (`Txl1Decoder::work_units`, about a byte hashed or searched each)
/// between yields to the runtime: well under a millisecond of CPU.
const DECODE_SLICE_WORK: u64 = 256 * 1024;

/// How one open device stopped delivering.
enum LineEnd {
    Shutdown,
    PipelineClosed,
    /// Reads returned 0 bytes or an error: the device went away.
    Disconnected(String),
    /// No byte for the stall timeout.
    Stalled,
}

impl SerialSource {
    /// The device path to open now: the literal path, or the first match of the glob.
    pub fn resolve_path(&self) -> Result<PathBuf, String> {
        if !self.path.contains(['*', '?', '[']) {
            return Ok(PathBuf::from(&self.path));
        }
        let matches = glob::glob(&self.path).map_err(|e| format!("bad glob {}: {e}", self.path))?;
        let mut found: Vec<PathBuf> = matches.filter_map(Result::ok).collect();
        found.sort();
        found
            .into_iter()
            .next()
            .ok_or_else(|| format!("no device matches {}", self.path))
    }

    fn open(&self) -> Result<(PathBuf, SerialStream), String> {
        let path = self.resolve_path()?;
        let builder = tokio_serial::new(path.to_string_lossy(), self.baud)
            .timeout(Duration::from_millis(100))
            .exclusive(true);
        match SerialStream::open(&builder) {
            Ok(stream) => Ok((path, stream)),
            Err(e) => Err(format!("cannot open {}: {e}", path.display())),
        }
    }

    /// Reads one open device until it stops delivering.
    async fn pump(
        &self,
        stream: &mut SerialStream,
        decoder: &mut Txl1Decoder,
        sink: &FrameSink,
        shutdown: &CancellationToken,
    ) -> LineEnd {
        let mut buf = vec![0u8; 64 * 1024];
        loop {
            let read = tokio::select! {
                biased;
                () = shutdown.cancelled() => return LineEnd::Shutdown,
                r = tokio::time::timeout(self.stall_timeout, stream.read(&mut buf)) => r,
            };
            let n = match read {
                Err(_elapsed) => return LineEnd::Stalled,
                Ok(Ok(0)) => {
                    return LineEnd::Disconnected("the device returned end of file".into());
                }
                Ok(Err(e)) => return LineEnd::Disconnected(format!("read failed: {e}")),
                Ok(Ok(n)) => n,
            };
            sink.metrics().add_counter("bytes_read", n as u64);
            decoder.push(&buf[..n]);
            // Decode this read in slices of bounded work, yielding between them and
            // after the read: hostile bytes (a frame claimed and failed whose span is
            // full of false magics) can hold megabytes of decoding, and the runtime
            // must still see shutdown, run the other sources and time out a stall.
            loop {
                match decoder.decode(DECODE_SLICE_WORK) {
                    Txl1Step::Frame(frame) => {
                        if sink
                            .send(SourceEvent::Range(Arc::new(frame.to_range_frame())))
                            .await
                            .is_err()
                        {
                            return LineEnd::PipelineClosed;
                        }
                    }
                    Txl1Step::NeedBytes => break,
                    Txl1Step::Paused => {
                        publish_counters(sink.metrics(), &decoder.counters());
                        tokio::task::yield_now().await;
                        if shutdown.is_cancelled() {
                            return LineEnd::Shutdown;
                        }
                    }
                }
            }
            publish_counters(sink.metrics(), &decoder.counters());
            tokio::task::yield_now().await;
        }
    }
}

fn publish_counters(metrics: &SourceMetrics, c: &Txl1Counters) {
    metrics.set_counter("frames_decoded", c.frames);
    metrics.set_counter("bytes_skipped", c.bytes_skipped);
    metrics.set_counter("bad_headers", c.bad_headers);
    metrics.set_counter("crc_errors", c.crc_errors);
    metrics.set_counter("bytes_in_bad_frames", c.bytes_in_bad_frames);
    metrics.set_counter("lost_frames", c.lost_frames);
    metrics.set_counter("seq_restarts", c.seq_restarts);
}

impl Source for SerialSource {
    fn name(&self) -> &str {
        &self.name
    }

    fn kind(&self) -> &'static str {
        "serial"
    }

    fn run(self: Box<Self>, sink: FrameSink, shutdown: CancellationToken) -> SourceFuture {
        Box::pin(async move { self.run_loop(sink, shutdown).await })
    }
}

impl SerialSource {
    async fn run_loop(
        self: Box<Self>,
        sink: FrameSink,
        shutdown: CancellationToken,
    ) -> Result<(), SourceError> {
        let metrics = sink.metrics().clone();
        // One decoder for the whole session, so sequence gaps across a reconnection
        // are still counted.
        let mut decoder = Txl1Decoder::new();
        let mut backoff = self.backoff_min;
        let mut opened_before = false;
        loop {
            if shutdown.is_cancelled() {
                return Ok(());
            }
            let (path, mut stream) = match self.open() {
                Ok(open) => open,
                Err(message) => {
                    metrics.set_state(SourceState::Reopening);
                    metrics.add_counter("open_failures", 1);
                    if metrics.last_error().as_deref() != Some(message.as_str()) {
                        tracing::warn!(source = %self.name, "{message}; retrying every {:?} at most", self.backoff_max);
                    }
                    metrics.report_error(message);
                    if sleep_or_shutdown(backoff, &shutdown).await {
                        return Ok(());
                    }
                    backoff = (backoff * 2).min(self.backoff_max);
                    continue;
                }
            };
            if opened_before {
                metrics.add_counter("reopens", 1);
            }
            opened_before = true;
            backoff = self.backoff_min;
            metrics.set_state(SourceState::Running);
            tracing::info!(source = %self.name, device = %path.display(), "serial device open");
            let end = self.pump(&mut stream, &mut decoder, &sink, &shutdown).await;
            publish_counters(&metrics, &decoder.counters());
            drop(stream);
            match end {
                LineEnd::Shutdown | LineEnd::PipelineClosed => return Ok(()),
                LineEnd::Disconnected(why) => {
                    metrics.add_counter("disconnects", 1);
                    let message = format!("{} disconnected: {why}", path.display());
                    tracing::warn!(source = %self.name, "{message}; reopening");
                    metrics.report_error(message);
                }
                LineEnd::Stalled => {
                    metrics.add_counter("stalls", 1);
                    let message = format!("{} silent for {:?}", path.display(), self.stall_timeout);
                    tracing::warn!(source = %self.name, "{message}; reopening");
                    metrics.report_error(message);
                }
            }
            metrics.set_state(SourceState::Reopening);
            if sleep_or_shutdown(self.backoff_min, &shutdown).await {
                return Ok(());
            }
        }
    }
}
