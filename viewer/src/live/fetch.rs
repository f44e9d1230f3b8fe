//! One model from a running daemon, for headless rendering (`render --connect`):
//! connect (retrying while the daemon starts), apply the snapshot, then live updates
//! until the model holds enough scans, ask for the data of every scan that was only
//! listed (a few requests at a time), and hand back the model (its GPU residency is
//! the renderer's budget's business). Deterministic: the same daemon model gives the
//! same result, however the messages were chunked.

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use texel::model::{Model, ScanId};
use texel::wire::Message;
use texel_client::{Applied, ClientError, Replica};

use super::connection::resolve;
use super::transport::Link;

/// Requests for scan data outstanding at once.
const MAX_IN_FLIGHT: usize = 8;

#[derive(Debug, thiserror::Error)]
pub enum FetchError {
    #[error("{addr}: {message}")]
    Failed { addr: String, message: String },
    #[error(
        "{addr}: no complete model with {wanted} scans within {waited:.0} s (have {have}{})",
        last.as_ref().map_or(String::new(), |l| format!("; last problem: {l}"))
    )]
    Timeout {
        addr: String,
        wanted: usize,
        have: usize,
        waited: f64,
        last: Option<String>,
    },
}

/// Connects to `addr` and returns the daemon's model once its snapshot is complete
/// and it holds at least `wait_scans` scans. Connection failures are retried until
/// `timeout`; a refusal (wrong token) or a stream that ends with fewer scans is an
/// error at once.
pub fn fetch_model(
    addr: &str,
    token: &str,
    wait_scans: usize,
    timeout: Duration,
) -> Result<Model, FetchError> {
    let failed = |message: String| FetchError::Failed {
        addr: addr.to_string(),
        message,
    };
    let start = Instant::now();
    let mut last_problem = None;
    let mut have = 0;
    while start.elapsed() < timeout {
        let left = timeout.saturating_sub(start.elapsed());
        let socket = match resolve(addr) {
            Ok(a) => a,
            Err(e) => return Err(failed(e)),
        };
        let io_timeout = left.clamp(Duration::from_millis(50), Duration::from_millis(500));
        // A short read timeout: requests go out between reads.
        let poll = Duration::from_millis(20);
        let mut client = match Link::connect(socket, token, "texel-viewer render", io_timeout) {
            Ok(c) => c,
            Err(ClientError::Refused(reason)) => {
                return Err(failed(format!("the daemon refused: {reason}")));
            }
            Err(e) => {
                last_problem = Some(e.to_string());
                std::thread::sleep(Duration::from_millis(100).min(left));
                continue;
            }
        };
        if let Err(e) = client.set_read_timeout(poll) {
            last_problem = Some(e.to_string());
            continue;
        }
        let mut replica = Replica::new();
        let mut requests = Requests::default();
        loop {
            if start.elapsed() >= timeout {
                break;
            }
            if replica.live
                && let Err(e) = requests.send(&mut client, &replica.model)
            {
                last_problem = Some(e.to_string());
                break;
            }
            let message = match client.next_message() {
                Ok(Some(m)) => m,
                Ok(None) => {
                    return Err(failed(format!(
                        "the daemon closed the stream with {} scans (waited for {wait_scans})",
                        replica.model.len()
                    )));
                }
                Err(ClientError::Timeout(_)) => continue,
                Err(e) => {
                    last_problem = Some(e.to_string());
                    break;
                }
            };
            match replica
                .apply(message)
                .map_err(|e| failed(format!("bad message: {e}")))?
            {
                Applied::Goodbye(reason) => {
                    return Err(failed(format!(
                        "the daemon ended the stream with {} scans (waited for {wait_scans}): {reason}",
                        replica.model.len()
                    )));
                }
                Applied::Reset { .. } => requests = Requests::default(),
                Applied::Unavailable { id, reason } => {
                    eprintln!("{addr}: scan {id} unavailable: {reason}");
                    requests.answered(id, false);
                }
                Applied::ScanAdded(id) => requests.answered(id, true),
                _ => {}
            }
            have = replica.model.len();
            if replica.live && have >= wait_scans.max(1) && requests.done(&replica.model) {
                return Ok(replica.model);
            }
        }
    }
    Err(FetchError::Timeout {
        addr: addr.to_string(),
        wanted: wait_scans,
        have,
        waited: start.elapsed().as_secs_f64(),
        last: last_problem,
    })
}

/// The requests for listed scans' data: each asked once, a few at a time.
#[derive(Default)]
struct Requests {
    in_flight: BTreeSet<ScanId>,
    /// Asked for (answered or not).
    asked: BTreeSet<ScanId>,
    unavailable: BTreeSet<ScanId>,
}

impl Requests {
    /// Asks for listed scans without data, up to the in-flight limit.
    fn send(&mut self, link: &mut Link, model: &Model) -> Result<(), ClientError> {
        for s in model.scans() {
            if self.in_flight.len() >= MAX_IN_FLIGHT {
                break;
            }
            if s.is_resident() || self.asked.contains(&s.id) {
                continue;
            }
            link.send(&Message::RequestScan { id: s.id })?;
            self.asked.insert(s.id);
            self.in_flight.insert(s.id);
        }
        Ok(())
    }

    fn answered(&mut self, id: ScanId, arrived: bool) {
        self.in_flight.remove(&id);
        if !arrived {
            self.unavailable.insert(id);
        }
    }

    /// Whether every listed scan has its data or cannot have it.
    fn done(&self, model: &Model) -> bool {
        self.in_flight.is_empty()
            && model
                .scans()
                .iter()
                .all(|s| s.is_resident() || self.unavailable.contains(&s.id))
    }
}
