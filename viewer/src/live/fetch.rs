//! One model from a running daemon, for headless rendering (`render --connect`):
//! connect (retrying while the daemon starts), apply the snapshot, then live updates
//! until the model holds enough scans and the data of every listed scan (the client
//! asks for it, a few requests at a time) is here or unavailable, and hand back the
//! model (its GPU residency is the renderer's budget's business). Deterministic: the same daemon model gives the
//! same result, however the messages were chunked.

use std::time::{Duration, Instant};

use texel::model::Model;
use texel_client::{Applied, BlockingClient, ClientError, Replica};

use super::connection::resolve;

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
    fetch_model_and_response(addr, token, wait_scans, timeout).map(|(model, _)| model)
}

/// [`fetch_model`], and the EO camera's response curve when the daemon serves one
/// (protocol version 4).
pub fn fetch_model_and_response(
    addr: &str,
    token: &str,
    wait_scans: usize,
    timeout: Duration,
) -> Result<(Model, Option<texel::radiance::EoResponse>), FetchError> {
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

        // The client requests every listed scan's data by itself as it reads.
        let mut client =
            match BlockingClient::connect(socket, token, "texel-viewer render", io_timeout) {
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

        let mut replica = Replica::new();
        loop {
            if start.elapsed() >= timeout {
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
                Applied::Unavailable { id, reason } => {
                    eprintln!("{addr}: scan {id} unavailable: {reason}");
                }
                _ => {}
            }
            // Listed scans arrive without their data; the client fetches them.
            have = replica.model.resident_len();
            if replica.complete() && have >= wait_scans.max(1) {
                return Ok((replica.model, replica.eo_response));
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
