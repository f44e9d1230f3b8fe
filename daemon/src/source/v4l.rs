//! The EO camera through V4L2 (`v4l` crate): opens the device, checks it is a
//! streaming capture device, negotiates pixel format, size and frame rate, and
//! streams memory-mapped buffers, converting each to RGB with the buffer's own
//! timestamp, and with the exposure the camera reports in manual exposure mode
//! ([`super::v4l_exposure`]). Every failure names the device and what was wrong; the
//! capture loop is thin, the conversions live in [`super::v4l_convert`].

use std::io;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use thiserror::Error;
use tokio_util::sync::CancellationToken;
use v4l::buffer::Type;
use v4l::capability::Flags;
use v4l::io::traits::CaptureStream;
use v4l::video::Capture;
use v4l::{Device, FourCC};

use super::v4l_convert::{PixelFormat, to_eo_frame};
use super::v4l_exposure::read_exposure;
use super::{FrameSink, Source, SourceError, SourceEvent, SourceFuture, SourceState};

/// The camera source's settings.
#[derive(Debug, Clone)]
pub struct V4lSource {
    pub name: String,
    pub device: PathBuf,
    pub format: PixelFormat,
    pub width: u32,
    pub height: u32,
    pub fps: u32,
    /// A dequeue that waits longer than this is an error.
    pub dequeue_timeout: Duration,
    pub buffers: u32,
}

/// What can go wrong with a camera.
#[derive(Debug, Error)]
pub enum V4lError {
    #[error("camera {path}: no such device")]
    Missing { path: String },
    #[error("camera {path}: permission denied (is the user in the video group?)")]
    PermissionDenied { path: String },
    #[error("camera {path}: busy (another program is using it)")]
    Busy { path: String },
    #[error("{path} is not a V4L2 camera: {reason}")]
    NotACamera { path: String, reason: String },
    #[error("camera {path} does not offer {wanted}; it offers: {available}")]
    UnsupportedFormat {
        path: String,
        wanted: String,
        available: String,
    },
    #[error("camera {path} set {got} when asked for {wanted}")]
    FormatRefused {
        path: String,
        wanted: String,
        got: String,
    },
    #[error("camera {path}: no frame within {timeout:?}")]
    DequeueTimeout { path: String, timeout: Duration },
    #[error("camera {path}: {what}: {source}")]
    Io {
        path: String,
        what: &'static str,
        source: io::Error,
    },
}

fn fourcc_name(f: &FourCC) -> String {
    f.str()
        .map_or_else(|_| format!("{:?}", f.repr), str::to_string)
}

/// Maps an I/O error of `what` on `path` to the error a user can act on.
fn classify(path: &Path, what: &'static str, e: io::Error) -> V4lError {
    let p = path.display().to_string();
    match e.kind() {
        io::ErrorKind::NotFound => V4lError::Missing { path: p },
        io::ErrorKind::PermissionDenied => V4lError::PermissionDenied { path: p },
        io::ErrorKind::ResourceBusy => V4lError::Busy { path: p },
        io::ErrorKind::TimedOut => V4lError::DequeueTimeout {
            path: p,
            timeout: Duration::ZERO,
        },
        _ => V4lError::Io {
            path: p,
            what,
            source: e,
        },
    }
}

/// An opened, configured camera.
pub struct OpenCamera {
    device: Device,
    pub path: PathBuf,
    pub format: PixelFormat,
    pub width: u32,
    pub height: u32,
    pub stride: u32,
}

impl V4lSource {
    /// Opens and configures the camera, or says precisely why it cannot.
    pub fn open(&self) -> Result<OpenCamera, V4lError> {
        let path = &self.device;
        let device = Device::with_path(path).map_err(|e| classify(path, "open", e))?;
        // A device node that is not a camera (/dev/null, a tty) fails QUERYCAP.
        let caps = device.query_caps().map_err(|e| V4lError::NotACamera {
            path: path.display().to_string(),
            reason: format!("VIDIOC_QUERYCAP failed: {e}"),
        })?;
        if !caps.capabilities.contains(Flags::VIDEO_CAPTURE) {
            return Err(V4lError::NotACamera {
                path: path.display().to_string(),
                reason: format!("{} ({}) has no video capture", caps.card, caps.driver),
            });
        }
        if !caps.capabilities.contains(Flags::STREAMING) {
            return Err(V4lError::NotACamera {
                path: path.display().to_string(),
                reason: format!("{} ({}) cannot stream", caps.card, caps.driver),
            });
        }
        let wanted = FourCC::new(&self.format.fourcc());
        let offered = device
            .enum_formats()
            .map_err(|e| classify(path, "listing formats", e))?;
        if !offered.iter().any(|d| d.fourcc == wanted) {
            return Err(V4lError::UnsupportedFormat {
                path: path.display().to_string(),
                wanted: fourcc_name(&wanted),
                available: offered
                    .iter()
                    .map(|d| format!("{} ({})", fourcc_name(&d.fourcc), d.description))
                    .collect::<Vec<_>>()
                    .join(", "),
            });
        }
        let mut format = device
            .format()
            .map_err(|e| classify(path, "reading the format", e))?;
        format.width = self.width;
        format.height = self.height;
        format.fourcc = wanted;
        let got = device
            .set_format(&format)
            .map_err(|e| classify(path, "setting the format", e))?;
        if got.fourcc != wanted || got.width != self.width || got.height != self.height {
            return Err(V4lError::FormatRefused {
                path: path.display().to_string(),
                wanted: format!("{}x{} {}", self.width, self.height, fourcc_name(&wanted)),
                got: format!("{}x{} {}", got.width, got.height, fourcc_name(&got.fourcc)),
            });
        }
        if self.fps > 0 {
            let params = v4l::video::capture::Parameters::with_fps(self.fps);
            // Not every driver can set a rate; the buffers' timestamps stay right.
            if let Err(e) = device.set_params(&params) {
                tracing::warn!(camera = %path.display(), "cannot set {} fps: {e}", self.fps);
            }
        }
        Ok(OpenCamera {
            device,
            path: path.clone(),
            format: self.format,
            width: got.width,
            height: got.height,
            stride: got.stride,
        })
    }

    /// Streams frames into `sink` until shutdown or an error.
    fn capture(&self, sink: &FrameSink, shutdown: &CancellationToken) -> Result<(), V4lError> {
        let camera = self.open()?;
        let path = camera.path.clone();
        let mut stream = v4l::io::mmap::Stream::with_buffers(
            &camera.device,
            Type::VideoCapture,
            self.buffers.max(2),
        )
        .map_err(|e| classify(&path, "mapping buffers", e))?;
        stream.set_timeout(self.dequeue_timeout);
        sink.metrics().set_state(SourceState::Running);
        tracing::info!(camera = %path.display(), "{}x{} {:?} streaming", camera.width, camera.height, camera.format);
        while !shutdown.is_cancelled() {
            let (buffer, meta) = stream.next().map_err(|e| match e.kind() {
                io::ErrorKind::TimedOut => V4lError::DequeueTimeout {
                    path: path.display().to_string(),
                    timeout: self.dequeue_timeout,
                },
                _ => classify(&path, "dequeuing a buffer", e),
            })?;
            let used = (meta.bytesused as usize).min(buffer.len());
            // V4L2 timestamps are CLOCK_MONOTONIC (the same clock TXL1 devices are
            // usually synchronised to by the host driver).
            let timestamp_ns = u64::try_from(meta.timestamp.sec).unwrap_or(0) * 1_000_000_000
                + u64::try_from(meta.timestamp.usec).unwrap_or(0) * 1_000;
            match to_eo_frame(
                camera.format,
                camera.width,
                camera.height,
                camera.stride,
                &buffer[..used],
                timestamp_ns,
            ) {
                Ok(mut frame) => {
                    // Read after the buffer: the controls as they stand for this frame
                    // (a camera applies a changed exposure a frame or two late).
                    frame.exposure = read_exposure(&camera.device);
                    if sink
                        .blocking_send(SourceEvent::Eo(Arc::new(frame)))
                        .is_err()
                    {
                        break;
                    }
                }
                Err(e) => {
                    sink.metrics().add_counter("bad_buffers", 1);
                    sink.metrics().report_error(e.to_string());
                }
            }
        }
        Ok(())
    }
}

impl Source for V4lSource {
    fn name(&self) -> &str {
        &self.name
    }

    fn kind(&self) -> &'static str {
        "v4l"
    }

    fn run(self: Box<Self>, sink: FrameSink, shutdown: CancellationToken) -> SourceFuture {
        Box::pin(async move {
            let name = self.name.clone();
            let metrics = sink.metrics().clone();
            let result = super::on_blocking_thread(&name, "camera thread", move || {
                self.capture(&sink, &shutdown)
            })
            .await?;
            match result {
                Ok(()) => {
                    metrics.set_state(SourceState::Ended);
                    Ok(())
                }
                Err(e) => {
                    metrics.set_state(SourceState::Failed);
                    metrics.report_error(e.to_string());
                    tracing::error!(source = %name, "{e}");
                    Err(SourceError::Fatal {
                        source_name: name,
                        message: e.to_string(),
                    })
                }
            }
        })
    }
}
