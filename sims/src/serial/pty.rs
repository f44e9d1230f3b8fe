//! The virtual lidar on a pseudo-terminal pair, on its own thread: the slave's path is
//! what a reader opens (like `/dev/ttyACM0`); the device waits for a reader before
//! streaming, keeps going when a reader closes and another opens, and carries out the
//! disconnect fault by closing the pair (and making a new one, under a new name, when
//! it is to reappear). With a `link` path, a symbolic link to the current slave is kept,
//! so a reader can reopen one fixed path.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError, sync_channel};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use serialport::{SerialPort, TTYPort};

use super::{InjectionLog, SerialError, StopSignal, StreamEnd, VirtualLidar};

/// How often the device looks for a reader while none has the port open.
const READER_POLL: Duration = Duration::from_millis(20);
/// Poll timeout of one write attempt (writes are retried until done or stopped).
const WRITE_POLL: Duration = Duration::from_millis(50);
/// Events kept for a consumer that does not read them.
const EVENT_QUEUE: usize = 256;

/// What the device did, for a console or a log.
#[derive(Debug, Clone, PartialEq)]
pub enum DeviceEvent {
    /// The device is at this path, waiting for a reader.
    Ready {
        path: String,
    },
    ReaderConnected,
    /// The reader closed the port (the device waits for the next one).
    ReaderGone,
    Stalling {
        seq: u32,
        seconds: f64,
    },
    /// The device disappeared before frame `seq`.
    Disconnected {
        seq: u32,
    },
    /// It came back under a new path.
    Reappeared {
        path: String,
    },
    /// The last frame was sent; the device stays open and silent.
    Finished,
}

/// A virtual lidar running on a pseudo-terminal.
pub struct PtyDevice {
    path: Arc<Mutex<String>>,
    stop: StopSignal,
    log: Arc<Mutex<InjectionLog>>,
    events: Receiver<DeviceEvent>,
    thread: Option<JoinHandle<Result<(), SerialError>>>,
}

impl PtyDevice {
    /// The path a reader opens now (the pseudo-terminal's slave; it changes when the
    /// device reappears after a disconnect).
    pub fn path(&self) -> String {
        self.path.lock().map(|p| p.clone()).unwrap_or_default()
    }

    /// A copy of the injection log so far.
    pub fn log(&self) -> InjectionLog {
        self.log.lock().map(|l| l.clone()).unwrap_or_default()
    }

    /// What the device did, in order (bounded: events no one reads are dropped).
    pub fn events(&self) -> &Receiver<DeviceEvent> {
        &self.events
    }

    pub fn is_running(&self) -> bool {
        self.thread.as_ref().is_some_and(|t| !t.is_finished())
    }

    /// Stops the device, closes the pseudo-terminal and returns the injection log.
    pub fn stop(mut self) -> Result<InjectionLog, SerialError> {
        self.stop.stop();
        self.join()
    }

    fn join(&mut self) -> Result<InjectionLog, SerialError> {
        if let Some(t) = self.thread.take() {
            match t.join() {
                Ok(result) => result?,
                Err(_) => {
                    return Err(SerialError::Device {
                        path: self.path(),
                        message: "the device thread panicked".into(),
                    });
                }
            }
        }
        Ok(self.log())
    }
}

impl Drop for PtyDevice {
    fn drop(&mut self) {
        self.stop.stop();
        let _ = self.join();
    }
}

/// A pseudo-terminal pair whose slave no one holds open yet.
fn open_pair(link: Option<&Path>) -> Result<(TTYPort, String), SerialError> {
    let device_error = |message: String| SerialError::Device {
        path: "pseudo-terminal".into(),
        message,
    };
    let (mut master, slave) =
        TTYPort::pair().map_err(|e| device_error(format!("cannot open a pair: {e}")))?;
    let path = slave
        .name()
        .ok_or_else(|| device_error("the slave has no name".into()))?;
    // Closing our slave handle lets the master see whether a reader has it open.
    drop(slave);
    master
        .set_timeout(WRITE_POLL)
        .map_err(|e| device_error(format!("cannot set a timeout: {e}")))?;
    if let Some(link) = link {
        let tmp = link.with_extension("tmp-link");
        let _ = std::fs::remove_file(&tmp);
        std::os::unix::fs::symlink(&path, &tmp)
            .and_then(|()| std::fs::rename(&tmp, link))
            .map_err(|e| SerialError::Device {
                path: link.display().to_string(),
                message: format!("cannot link it to {path}: {e}"),
            })?;
    }
    Ok((master, path))
}

/// Waits until a reader has the slave open; false when stopped first. With no slave
/// open the master reports a hang-up, which `write` of nothing turns into
/// `BrokenPipe`.
fn wait_for_reader(master: &mut TTYPort, stop: &StopSignal) -> bool {
    loop {
        match master.write(&[]) {
            Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => {
                if stop.sleep(READER_POLL) {
                    return false;
                }
            }
            // Writable (or full: someone is there and not reading yet).
            _ => return !stop.is_stopped(),
        }
    }
}

/// The master as a blocking writer: writes that time out (a reader that is slow to
/// read) are retried until done, the reader goes away (`BrokenPipe`) or a stop.
struct PatientWriter<'a> {
    port: &'a mut TTYPort,
    stop: &'a StopSignal,
}

impl Write for PatientWriter<'_> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        loop {
            match self.port.write(buf) {
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::TimedOut
                            | std::io::ErrorKind::WouldBlock
                            | std::io::ErrorKind::Interrupted
                    ) && !self.stop.is_stopped() => {}
                other => return other,
            }
        }
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

fn send(events: &SyncSender<DeviceEvent>, e: DeviceEvent) {
    if let Err(TrySendError::Full(_)) = events.try_send(e) {
        // No one is reading events: drop them rather than block the device.
    }
}

/// Runs `lidar` on a new pseudo-terminal pair on its own thread; returns once the
/// slave's path is known. `link`: a symbolic link kept pointing at the current slave.
pub fn spawn_pty(mut lidar: VirtualLidar, link: Option<PathBuf>) -> Result<PtyDevice, SerialError> {
    let (master, path) = open_pair(link.as_deref())?;
    let shared_path = Arc::new(Mutex::new(path.clone()));
    let stop = StopSignal::new();
    let log = lidar.log_handle();
    let (tx, rx) = sync_channel(EVENT_QUEUE);
    send(&tx, DeviceEvent::Ready { path });
    lidar.events = Some(tx.clone());
    let thread = {
        let (stop, shared_path) = (stop.clone(), shared_path.clone());
        std::thread::Builder::new()
            .name("virtual-lidar".into())
            .spawn(move || {
                drive(
                    &mut lidar,
                    master,
                    link.as_deref(),
                    &stop,
                    &shared_path,
                    &tx,
                )
            })
            .map_err(|e| SerialError::Device {
                path: "pseudo-terminal".into(),
                message: format!("cannot start the device thread: {e}"),
            })?
    };
    Ok(PtyDevice {
        path: shared_path,
        stop,
        log,
        events: rx,
        thread: Some(thread),
    })
}

fn drive(
    lidar: &mut VirtualLidar,
    mut master: TTYPort,
    link: Option<&Path>,
    stop: &StopSignal,
    path: &Mutex<String>,
    events: &SyncSender<DeviceEvent>,
) -> Result<(), SerialError> {
    loop {
        if !wait_for_reader(&mut master, stop) {
            return Ok(());
        }
        send(events, DeviceEvent::ReaderConnected);
        let end = {
            let mut out = PatientWriter {
                port: &mut master,
                stop,
            };
            lidar.run(&mut out, stop)
        };
        match end {
            Ok(StreamEnd::Stopped) => return Ok(()),
            Ok(StreamEnd::Finished) => {
                send(events, DeviceEvent::Finished);
                // Stay open and silent until stopped, like a device that is done.
                while !stop.sleep(Duration::from_secs(3600)) {}
                return Ok(());
            }
            Ok(StreamEnd::Disconnect { seq }) => {
                drop(master);
                send(events, DeviceEvent::Disconnected { seq });
                let Some(delay) = lidar.config().faults.reappear_after_s else {
                    while !stop.sleep(Duration::from_secs(3600)) {}
                    return Ok(());
                };
                if stop.sleep(Duration::from_secs_f64(delay)) {
                    return Ok(());
                }
                let (m, p) = open_pair(link)?;
                master = m;
                if let Ok(mut shared) = path.lock() {
                    shared.clone_from(&p);
                }
                lidar.record_reappearance(&p);
                send(events, DeviceEvent::Reappeared { path: p });
            }
            Err(SerialError::Write(e)) if e.kind() == std::io::ErrorKind::BrokenPipe => {
                lidar.record_reader_gone(lidar.next_seq().wrapping_sub(1));
                send(events, DeviceEvent::ReaderGone);
            }
            Err(e) => return Err(e),
        }
    }
}
