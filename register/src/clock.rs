//! Time measurement for registration reports: wall time, and the CPU time of the
//! process (all its threads, so work handed to the rayon pool counts), which on a
//! shared, loaded machine measures what the work costs without the time spent
//! waiting for a core.

use std::time::{Duration, Instant};

fn duration(t: rustix::time::Timespec) -> Option<Duration> {
    let secs = u64::try_from(t.tv_sec).ok()?;
    let nanos = u32::try_from(t.tv_nsec).ok()?;
    Some(Duration::new(secs, nanos))
}

/// CPU time the calling thread has run (`CLOCK_THREAD_CPUTIME_ID`).
pub fn thread_cpu_time() -> Option<Duration> {
    duration(rustix::time::clock_gettime(
        rustix::time::ClockId::ThreadCPUTime,
    ))
}

/// CPU time all the process's threads have run, ended ones included
/// (`CLOCK_PROCESS_CPUTIME_ID`): work handed to the rayon pool counts.
pub fn process_cpu_time() -> Option<Duration> {
    duration(rustix::time::clock_gettime(
        rustix::time::ClockId::ProcessCPUTime,
    ))
}

/// A stopwatch of wall and process CPU time.
#[derive(Debug, Clone, Copy)]
pub struct Stopwatch {
    wall: Instant,
    cpu: Option<Duration>,
}

/// What a [`Stopwatch`] measured, in milliseconds; `cpu_ms` falls back to the wall
/// time where process CPU time is not available.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Elapsed {
    pub wall_ms: f64,
    pub cpu_ms: f64,
}

impl Stopwatch {
    pub fn start() -> Self {
        Self {
            cpu: process_cpu_time(),
            wall: Instant::now(),
        }
    }

    pub fn elapsed(&self) -> Elapsed {
        let wall_ms = self.wall.elapsed().as_secs_f64() * 1000.0;
        let cpu_ms = match (self.cpu, process_cpu_time()) {
            (Some(a), Some(b)) => b.saturating_sub(a).as_secs_f64() * 1000.0,
            _ => wall_ms,
        };
        Elapsed { wall_ms, cpu_ms }
    }
}

/// Reports use the project's one quantile (nearest rank).
pub use texel::stats::quantile;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_time_advances_with_work_and_quantiles_pick_ranks() {
        // Other test threads run concurrently, so the work is checked on this
        // thread's own clock.
        let before = thread_cpu_time().unwrap();
        let watch = Stopwatch::start();
        let mut x = 0u64;
        for i in 0..20_000_000u64 {
            x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(i));
        }
        assert!(x != 1);
        let spent = thread_cpu_time().unwrap().saturating_sub(before);
        assert!(spent > Duration::from_micros(100), "{spent:?}");
        let e = watch.elapsed();
        assert!(
            e.wall_ms > 0.0 && e.cpu_ms >= spent.as_secs_f64() * 1000.0 * 0.99,
            "{e:?}"
        );
        assert!(process_cpu_time().is_some());
        assert_eq!(quantile(&[3.0, 1.0, 2.0], 0.5), 2.0);
        assert_eq!(quantile(&[], 0.5), 0.0);
        assert_eq!(quantile(&[1.0, f64::NAN, 5.0], 1.0), 5.0);
    }
}
