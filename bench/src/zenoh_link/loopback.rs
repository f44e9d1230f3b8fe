//! Part 1 of `texel-bench zenoh`: loopback runs (a live viewer, then a late joiner)
//! and their report against the TCP stream.

use super::*;

/// A live viewer's latencies (ms) and the scans left out of them (added before the
/// viewer was ready).
pub(super) fn latencies_ms(camera: &Camera, viewing: &Viewing) -> (Vec<f64>, usize) {
    let mut out = Vec::new();
    let mut early = 0;
    for (id, &at) in &viewing.arrivals {
        let Some(&added) = camera.added.get(id) else {
            continue;
        };
        if added < viewing.ready_ns {
            early += 1;
            continue;
        }
        out.push(at.saturating_sub(added) as f64 * 1e-6);
    }
    (out, early)
}

/// One loopback run: a live viewer, then a late joiner, each of `path`.
pub(super) struct Run {
    pub(super) path: Via,
    pub(super) camera: Camera,
    pub(super) live: Viewing,
    pub(super) late: Viewing,
}

impl Run {
    pub(super) fn latency(&self) -> (f64, f64) {
        percentiles(&latencies_ms(&self.camera, &self.live).0)
    }

    /// First scan added to the whole model at the live viewer (s).
    pub(super) fn live_whole_s(&self) -> f64 {
        secs(
            self.live
                .last_arrival_ns()
                .saturating_sub(self.camera.first_added_ns()),
        )
    }

    pub(super) fn late_scans_per_s(&self) -> f64 {
        self.late.arrivals.len() as f64 / self.late.whole_model_s().max(1e-9)
    }

    pub(super) fn late_bytes_per_s(&self) -> f64 {
        self.late.link_bytes as f64 / self.late.whole_model_s().max(1e-9)
    }

    pub(super) fn summary_line(&self) -> String {
        let (p50, p99) = self.latency();
        format!(
            "live: {} scans, latency p50 {p50:.1} ms, p99 {p99:.1} ms, {:.2} MB; late joiner: \
             {} scans in {:.2} s, {:.2} MB",
            self.live.arrivals.len(),
            self.live.link_bytes as f64 / 1e6,
            self.late.arrivals.len(),
            self.late.whole_model_s(),
            self.late.link_bytes as f64 / 1e6
        )
    }
}

pub(super) async fn loopback_run(args: &Args, scene: &Path, path: Via) -> Result<Run> {
    let config = session_config(args, scene, "127.0.0.1:0", None, "tcp/127.0.0.1:0", None)?;
    let shutdown = CancellationToken::new();
    let session = start_session(config, shutdown.clone()).await?;
    let _stop = shutdown.clone().drop_guard();
    let (added, before_tap) = tap(&session.hub)?;
    let tcp = session.local_addr.context("the session does not serve")?;
    let zenoh = session
        .zenoh_locators
        .first()
        .cloned()
        .context("the session publishes on no Zenoh endpoint")?;
    let opts = ViewOptions::of(args);
    let view = |late: bool| {
        let zenoh = zenoh.clone();
        async move {
            match path {
                Via::Tcp => view_tcp(&tcp.to_string(), "", &opts).await,
                Via::Zenoh => view_zenoh(&zenoh, None, &opts).await,
            }
            .with_context(|| {
                format!(
                    "the {} viewer ({})",
                    path.name(),
                    if late { "late" } else { "live" }
                )
            })
        }
    };
    let live = view(false).await?;
    tokio::time::timeout(Duration::from_secs(60), session.sources_done.cancelled())
        .await
        .context("the camera did not finish within 60 s of the live viewer")?;
    let late = view(true).await?;
    shutdown.cancel();
    let summary = session.wait().await?;
    Ok(Run {
        path,
        camera: Camera {
            added: taken(&added),
            before_tap,
            status: summary.status,
        },
        live,
        late,
    })
}

/// One figure of a run.
pub(super) type Figure = dyn Fn(&Run) -> f64;

pub(super) fn loopback_report(
    out: &mut String,
    args: &Args,
    runs: &[Run],
    tcp: &[&Run],
    zenoh: &[&Run],
) {
    let mut w = |s: String| {
        let _ = writeln!(out, "{s}");
    };
    w("## Zenoh against the TCP stream (`texel-bench zenoh`)\n".into());
    w(format!(
        "Camera: in-process daemon, `{}` first {} frames, seed 1, rendered before the \
         first is sent, then sent at 10 Hz; scans placed at the true poses (no registration), \
         `keep-newest`, JPEG textures; Zenoh peer on tcp/127.0.0.1, no multicast \
         scouting; the daemon's runtime has {} worker threads, the Zenoh gateway and the \
         viewers run on it too. {} cores. Runs interleaved TCP, Zenoh, ... ({} of each).\n",
        args.scene
            .file_stem()
            .map_or("?".into(), |s| s.to_string_lossy()),
        args.frames,
        daemon_workers(args),
        cores(),
        args.repeats
    ));
    w("Each run:\n".into());
    w(
        "| run | path | live: latency p50 / p99 (ms) | live: whole model after the first scan (s) | \
         live: link MB | late joiner: whole model (s) | scans/s | MB/s | link kB per scan |"
            .into(),
    );
    w("|---|---|---|---|---|---|---|---|---|".into());
    for (i, r) in runs.iter().enumerate() {
        let (p50, p99) = r.latency();
        w(format!(
            "| {} | {} | {p50:.1} / {p99:.1} | {:.2} | {:.2} | {:.3} | {:.1} | {:.1} | {:.0} |",
            i + 1,
            r.path.name(),
            r.live_whole_s(),
            r.live.link_bytes as f64 / 1e6,
            r.late.whole_model_s(),
            r.late_scans_per_s(),
            r.late_bytes_per_s() / 1e6,
            r.late.link_bytes as f64 / 1e3 / r.late.arrivals.len().max(1) as f64
        ));
    }
    let med = |runs: &[&Run], f: &dyn Fn(&Run) -> f64| median(runs.iter().map(|r| f(r)));
    let figures: [(&str, &Figure, usize); 9] = [
        ("live: latency p50 (ms)", &|r| r.latency().0, 1),
        ("live: latency p99 (ms)", &|r| r.latency().1, 1),
        (
            "live: whole model after the first scan (s)",
            &|r| r.live_whole_s(),
            2,
        ),
        (
            "live: link bytes (MB)",
            &|r| r.live.link_bytes as f64 / 1e6,
            2,
        ),
        (
            "late joiner: listing (ms; Zenoh: session, camera found, model asked)",
            &|r| secs(r.late.ready_ns.saturating_sub(r.late.started_ns)) * 1e3,
            1,
        ),
        (
            "late joiner: whole model (s)",
            &|r| r.late.whole_model_s(),
            3,
        ),
        ("late joiner: scans/s", &|r| r.late_scans_per_s(), 1),
        ("late joiner: MB/s", &|r| r.late_bytes_per_s() / 1e6, 1),
        (
            "late joiner: link bytes (MB)",
            &|r| r.late.link_bytes as f64 / 1e6,
            2,
        ),
    ];
    w(format!("\nMedians of {} runs each:\n", args.repeats));
    w("| figure | TCP (baseline) | Zenoh | Zenoh / TCP |".into());
    w("|---|---|---|---|".into());
    for (name, f, digits) in figures {
        let (t, z) = (med(tcp, f), med(zenoh, f));
        w(format!(
            "| {name} | {t:.digits$} | {z:.digits$} | {:.2} |",
            z / t
        ));
    }
    let incomplete: Vec<String> = runs
        .iter()
        .enumerate()
        .filter(|(_, r)| !got_all(&r.camera, &r.live) || !got_all(&r.camera, &r.late))
        .map(|(i, r)| {
            format!(
                "run {} ({}): live {} / late {} of {} scans, unavailable: {:?} / {:?}",
                i + 1,
                r.path.name(),
                r.live.arrivals.len(),
                r.late.arrivals.len(),
                args.frames,
                r.live.unavailable,
                r.late.unavailable
            )
        })
        .collect();
    let early: usize = runs
        .iter()
        .map(|r| latencies_ms(&r.camera, &r.live).1 + r.camera.before_tap)
        .sum();
    w(format!(
        "\nEvery viewer got the whole model: {}; scans added before the live viewer was \
         ready (left out of the latencies): {early}",
        if incomplete.is_empty() {
            "yes".to_string()
        } else {
            format!("no: {}", incomplete.join("; "))
        }
    ));
    w("\nThe camera in the same runs (medians):\n".into());
    camera_header(&mut w);
    for (name, rs) in [
        ("loopback, TCP viewer", tcp),
        ("loopback, Zenoh viewer", zenoh),
    ] {
        let cams: Vec<&Camera> = rs.iter().map(|r| &r.camera).collect();
        w(camera_row(name, &cams));
    }
}
