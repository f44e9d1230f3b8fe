//! How the gateway gets a scan's data it does not hold, per camera: it first waits
//! a moment for the live put that follows a new listing (asking as well would carry
//! the scan twice over the link), then asks the camera by id, a few scans at a time,
//! with timeouts sized from the link's measured rate, and asks again before it
//! gives up. A link at 2 Mbit/s takes seconds per scan: a fixed timeout on many
//! queries at once would turn a slow link into missing scans.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use texel::model::ScanId;
use tokio::sync::{Notify, OwnedSemaphorePermit, Semaphore};

/// Scan queries under way per camera; the rest wait their turn (without their
/// timeouts running), so each one gets the link's whole rate between them.
pub const SCAN_QUERIES_PER_CAMERA: usize = 2;
/// Times a scan is asked for before the viewer is told it is unavailable.
pub const QUERY_ATTEMPTS: u32 = 3;
/// The longest a single query may be given.
const MAX_QUERY_TIMEOUT: Duration = Duration::from_secs(300);
/// How long to wait for a just-listed scan's live data before the link's rate is
/// known, and the bounds of that wait once it is.
const DEFAULT_LIVE_WAIT: Duration = Duration::from_secs(2);
const MIN_LIVE_WAIT: Duration = Duration::from_millis(500);
const MAX_LIVE_WAIT: Duration = Duration::from_secs(30);
/// New listings remembered per camera (their data normally follow at once).
const MAX_LISTED: usize = 4096;
/// Weight of a new rate observation in the running estimate.
const RATE_WEIGHT: f64 = 0.3;

/// A running estimate of a camera's link rate in bytes per second, from the scans'
/// data seen arriving (live, and in answers to queries).
#[derive(Debug, Default, Clone, Copy)]
pub struct LinkRate {
    bytes_per_s: Option<f64>,
}

impl LinkRate {
    /// Adds one observation: `bytes` took `elapsed`. Ignored when too short to time.
    pub fn observe(&mut self, bytes: usize, elapsed: Duration) {
        let secs = elapsed.as_secs_f64();
        if bytes == 0 || secs < 1e-3 {
            return;
        }
        let rate = bytes as f64 / secs;
        if !rate.is_finite() {
            return;
        }
        self.bytes_per_s = Some(match self.bytes_per_s {
            Some(old) => (1.0 - RATE_WEIGHT) * old + RATE_WEIGHT * rate,
            None => rate,
        });
    }

    /// The estimated rate, when one has been seen.
    pub fn bytes_per_s(&self) -> Option<f64> {
        self.bytes_per_s
    }

    /// How long `bytes` should take at the estimated rate; `None` before any
    /// observation.
    pub fn expected(&self, bytes: u64) -> Option<Duration> {
        let rate = self.bytes_per_s.filter(|r| r.is_finite() && *r > 0.0)?;
        Duration::try_from_secs_f64(bytes as f64 / rate).ok()
    }
}

struct CameraLink {
    queries: Arc<Semaphore>,
    rate: LinkRate,
    /// Own ids of scans listed live whose data have not arrived, with when.
    listed_at: HashMap<ScanId, Instant>,
}

impl CameraLink {
    fn new() -> Self {
        Self {
            queries: Arc::new(Semaphore::new(SCAN_QUERIES_PER_CAMERA)),
            rate: LinkRate::default(),
            listed_at: HashMap::new(),
        }
    }
}

/// Every followed camera's link, and a signal for data arriving.
#[derive(Default)]
pub(crate) struct Links {
    by_camera: Mutex<HashMap<String, CameraLink>>,
    /// Woken whenever a scan's data arrive live.
    pub data_arrived: Notify,
}

/// How one scan is to be asked for.
pub(crate) struct QueryPlan {
    /// The camera's turn to ask (held for the whole of the asking).
    pub permit: OwnedSemaphorePermit,
    /// One timeout per attempt, growing.
    pub timeouts: Vec<Duration>,
}

impl Links {
    fn lock(&self) -> MutexGuard<'_, HashMap<String, CameraLink>> {
        self.by_camera
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Camera `prefix` listed scan `id` live: its data should follow.
    pub fn listed(&self, prefix: &str, id: ScanId) {
        let mut links = self.lock();
        let link = links
            .entry(prefix.to_string())
            .or_insert_with(CameraLink::new);
        if link.listed_at.len() >= MAX_LISTED {
            // Data that never came (dropped on the link): forget the oldest half.
            let mut times: Vec<Instant> = link.listed_at.values().copied().collect();
            times.sort_unstable();
            if let Some(&cut) = times.get(times.len() / 2) {
                link.listed_at.retain(|_, t| *t > cut);
            }
        }
        link.listed_at.insert(id, Instant::now());
    }

    /// Scan `id`'s data (`bytes` long) arrived live from camera `prefix`.
    pub fn data_arrived(&self, prefix: &str, id: ScanId, bytes: usize) {
        {
            let mut links = self.lock();
            let link = links
                .entry(prefix.to_string())
                .or_insert_with(CameraLink::new);
            if let Some(listed) = link.listed_at.remove(&id) {
                link.rate.observe(bytes, listed.elapsed());
            }
        }
        self.data_arrived.notify_waiters();
    }

    /// Until when to wait for scan `id`'s live data (`bytes` long) before asking for
    /// it; `None` when it was not just listed live (or has waited long enough).
    pub fn live_wait_until(&self, prefix: &str, id: ScanId, bytes: u64) -> Option<Instant> {
        let links = self.lock();
        let link = links.get(prefix)?;
        let listed = *link.listed_at.get(&id)?;
        let wait = match link.rate.expected(bytes) {
            Some(expected) => (expected * 2 + MIN_LIVE_WAIT).clamp(MIN_LIVE_WAIT, MAX_LIVE_WAIT),
            None => DEFAULT_LIVE_WAIT,
        };
        let until = listed + wait;
        (until > Instant::now()).then_some(until)
    }

    /// Waits for camera `prefix`'s turn to ask for a scan of `bytes`, and plans the
    /// attempts: each gets at least `base`, or three times what the scans queued
    /// before it and it should take at the measured rate, doubling per attempt.
    pub async fn plan_query(&self, prefix: &str, bytes: u64, base: Duration) -> Option<QueryPlan> {
        let queries = {
            let mut links = self.lock();
            let link = links
                .entry(prefix.to_string())
                .or_insert_with(CameraLink::new);
            Arc::clone(&link.queries)
        };
        let permit = queries.acquire_owned().await.ok()?;
        let expected = self
            .lock()
            .get(prefix)
            .and_then(|l| l.rate.expected(bytes * SCAN_QUERIES_PER_CAMERA as u64));
        Some(QueryPlan {
            permit,
            timeouts: query_timeouts(base, expected),
        })
    }

    /// A query for `bytes` was answered after `elapsed`.
    pub fn query_answered(&self, prefix: &str, bytes: usize, elapsed: Duration) {
        if let Some(link) = self.lock().get_mut(prefix) {
            link.rate.observe(bytes, elapsed);
        }
    }

    /// The measured rate of camera `prefix`'s link, bytes per second.
    pub fn rate(&self, prefix: &str) -> Option<f64> {
        self.lock().get(prefix)?.rate.bytes_per_s()
    }
}

/// The timeouts of [`QUERY_ATTEMPTS`] attempts: the first `max(base, 3 x expected)`,
/// each next one double, none past [`MAX_QUERY_TIMEOUT`].
pub fn query_timeouts(base: Duration, expected: Option<Duration>) -> Vec<Duration> {
    let first = expected
        .map_or(base, |e| base.max(e.saturating_mul(3)))
        .min(MAX_QUERY_TIMEOUT);
    (0..QUERY_ATTEMPTS)
        .map(|a| first.saturating_mul(1 << a).min(MAX_QUERY_TIMEOUT))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rate_follows_observations_and_ignores_untimeable_ones() {
        let mut rate = LinkRate::default();
        assert_eq!(rate.expected(1000), None);
        rate.observe(1000, Duration::from_micros(10));
        rate.observe(0, Duration::from_secs(1));
        assert_eq!(rate.bytes_per_s(), None);
        rate.observe(250_000, Duration::from_secs(1));
        assert_eq!(rate.bytes_per_s(), Some(250_000.0));
        // A slower link pulls the estimate down, by the observation's weight.
        rate.observe(125_000, Duration::from_secs(1));
        let r = rate.bytes_per_s().unwrap_or(0.0);
        assert!((r - 212_500.0).abs() < 1e-6, "{r}");
        let e = rate.expected(425_000).unwrap_or_default();
        assert!((e.as_secs_f64() - 2.0).abs() < 1e-9, "{e:?}");
    }

    #[test]
    fn timeouts_grow_from_the_larger_of_base_and_the_expected_time() {
        let base = Duration::from_secs(10);
        assert_eq!(
            query_timeouts(base, None),
            [10, 20, 40].map(Duration::from_secs)
        );
        assert_eq!(
            query_timeouts(base, Some(Duration::from_secs(8))),
            [24, 48, 96].map(Duration::from_secs)
        );
        assert!(
            query_timeouts(base, Some(Duration::from_secs(1_000_000)))
                .iter()
                .all(|t| *t == MAX_QUERY_TIMEOUT)
        );
    }

    #[test]
    fn a_just_listed_scan_is_waited_for_until_its_data_arrive() {
        let links = Links::default();
        assert!(links.live_wait_until("texel/s/a", 7, 1_000_000).is_none());
        links.listed("texel/s/a", 7);
        let until = links.live_wait_until("texel/s/a", 7, 1_000_000);
        assert!(until.is_some_and(|u| u > Instant::now()));
        std::thread::sleep(Duration::from_millis(20));
        links.data_arrived("texel/s/a", 7, 1_000_000);
        assert!(links.live_wait_until("texel/s/a", 7, 1_000_000).is_none());
        // The listing-to-data interval gave the link's rate: at most 1 MB in 20 ms.
        let rate = links.rate("texel/s/a").unwrap_or(f64::INFINITY);
        assert!(rate <= 50e6 && rate > 0.0, "{rate}");
    }

    #[test]
    fn forgotten_listings_stay_bounded() {
        let links = Links::default();
        for id in 0..(MAX_LISTED as ScanId * 3) {
            links.listed("texel/s/a", id);
        }
        let held = links
            .lock()
            .get("texel/s/a")
            .map_or(0, |l| l.listed_at.len());
        assert!(held <= MAX_LISTED, "{held}");
    }

    #[tokio::test]
    async fn queries_take_turns_per_camera() {
        let links = Links::default();
        let base = Duration::from_secs(10);
        let mut held = Vec::new();
        for _ in 0..SCAN_QUERIES_PER_CAMERA {
            held.push(links.plan_query("texel/s/a", 10, base).await);
        }
        // The camera's turns are taken; another camera's are not.
        let waiting = tokio::time::timeout(
            Duration::from_millis(50),
            links.plan_query("texel/s/a", 10, base),
        )
        .await;
        assert!(waiting.is_err());
        let other = links.plan_query("texel/s/b", 10, base).await;
        assert!(other.is_some());
        held.pop();
        let next = tokio::time::timeout(
            Duration::from_millis(500),
            links.plan_query("texel/s/a", 10, base),
        )
        .await;
        assert!(next.is_ok_and(|p| p.is_some()));
    }
}
