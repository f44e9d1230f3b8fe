//! Part 2 of `texel-bench zenoh`: the rate-limited link (a network namespace, a
//! veth pair shaped with `tc tbf`), the viewer run inside it (`--viewer-only`), and
//! the report.

use super::*;

/// A network namespace joined to this one by a veth pair whose end here is shaped;
/// removed when dropped.
pub(super) struct Netns {
    pub(super) name: String,
    pub(super) host_if: String,
    /// Made so far (what drop removes).
    pub(super) made_ns: bool,
    pub(super) made_link: bool,
}

pub(super) fn ip(args: &[&str]) -> Result<()> {
    sh("ip", args)
}

pub(super) fn sh(program: &str, args: &[&str]) -> Result<()> {
    let out = Command::new(program)
        .args(args)
        .output()
        .with_context(|| format!("running {program}"))?;
    if !out.status.success() {
        bail!(
            "`{program} {}` failed: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    Ok(())
}

impl Netns {
    pub(super) fn create(rate_kbit: u32) -> Result<Self> {
        let pid = std::process::id();
        let mut net = Self {
            name: format!("texel-bench-{pid}"),
            host_if: format!("tbz{pid}a"),
            made_ns: false,
            made_link: false,
        };
        let viewer_if = format!("tbz{pid}b");
        let used = Command::new("ip")
            .args(["-o", "addr", "show", "to", &format!("{HOST_IP}/24")])
            .output()
            .context("running ip (iproute2)")?;
        if !used.stdout.is_empty() {
            bail!(
                "{HOST_IP}/24 is in use here already ({}); a leftover of an interrupted run \
                 goes with `ip link del IFACE`",
                String::from_utf8_lossy(&used.stdout).trim()
            );
        }
        ip(&["netns", "add", &net.name])?;
        net.made_ns = true;
        ip(&[
            "link",
            "add",
            &net.host_if,
            "type",
            "veth",
            "peer",
            "name",
            &viewer_if,
            "netns",
            &net.name,
        ])?;
        net.made_link = true;
        ip(&["addr", "add", &format!("{HOST_IP}/24"), "dev", &net.host_if])?;
        ip(&["link", "set", &net.host_if, "up"])?;
        let inside = |a: &[&str]| {
            let mut all = vec!["netns", "exec", &net.name, "ip"];
            all.extend_from_slice(a);
            ip(&all)
        };
        inside(&["addr", "add", &format!("{VIEWER_IP}/24"), "dev", &viewer_if])?;
        inside(&["link", "set", &viewer_if, "up"])?;
        inside(&["link", "set", "lo", "up"])?;
        sh(
            "tc",
            &[
                "qdisc",
                "add",
                "dev",
                &net.host_if,
                "root",
                "tbf",
                "rate",
                &format!("{rate_kbit}kbit"),
                "burst",
                "32kbit",
                "latency",
                "400ms",
            ],
        )?;
        Ok(net)
    }

    /// Bytes sent out of the shaped end (every packet, headers included).
    pub(super) fn host_tx_bytes(&self) -> Option<u64> {
        std::fs::read_to_string(format!(
            "/sys/class/net/{}/statistics/tx_bytes",
            self.host_if
        ))
        .ok()?
        .trim()
        .parse()
        .ok()
    }

    /// What tbf reports for the shaped end (`tc -s qdisc`): sent, dropped, overlimits.
    pub(super) fn qdisc_stats(&self) -> String {
        Command::new("tc")
            .args(["-s", "qdisc", "show", "dev", &self.host_if])
            .output()
            .map(|o| {
                String::from_utf8_lossy(&o.stdout)
                    .lines()
                    .map(str::trim)
                    .find(|l| l.starts_with("Sent"))
                    .unwrap_or("")
                    .to_string()
            })
            .unwrap_or_default()
    }
}

impl Drop for Netns {
    fn drop(&mut self) {
        // Deleting one end of a veth pair deletes both.
        if self.made_link
            && let Err(e) = ip(&["link", "del", &self.host_if])
        {
            eprintln!("zenoh: cleaning up: {e:#}");
        }
        if self.made_ns
            && let Err(e) = ip(&["netns", "del", &self.name])
        {
            eprintln!("zenoh: cleaning up: {e:#}");
        }
    }
}

/// A child process killed when dropped (unless it has ended).
pub(super) struct ChildGuard(Child);

impl Drop for ChildGuard {
    fn drop(&mut self) {
        if let Ok(None) = self.0.try_wait() {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
}

/// One run behind the rate-limited link.
pub(super) struct Shaped {
    pub(super) via: Via,
    pub(super) camera: Camera,
    pub(super) viewing: Viewing,
    /// Bytes out of the shaped end during the run (every packet, headers included).
    pub(super) host_tx_bytes: Option<u64>,
    /// When the camera's sources ended, after its first scan (s).
    pub(super) camera_done_s: f64,
}

impl Shaped {
    pub(super) fn whole_s(&self) -> Option<f64> {
        got_all(&self.camera, &self.viewing).then(|| {
            secs(
                self.viewing
                    .last_arrival_ns()
                    .saturating_sub(self.camera.first_added_ns()),
            )
        })
    }
}

/// Whether the viewer got every scan the camera added.
pub(super) fn got_all(camera: &Camera, viewing: &Viewing) -> bool {
    !camera.added.is_empty()
        && camera
            .added
            .keys()
            .all(|id| viewing.arrivals.contains_key(id))
}

pub(super) async fn shaped_run(args: &Args, scene: &Path, net: &Netns, via: Via) -> Result<Shaped> {
    let dir = tempfile::tempdir()?;
    let secret = format!("texel-bench-{}-{}", std::process::id(), now_ns());
    let users = dir.path().join("users.txt");
    std::fs::write(&users, format!("{VIEWER_USER}:{secret}\n"))?;
    let secret_file = dir.path().join("secret.txt");
    std::fs::write(&secret_file, format!("{secret}\n"))?;
    // The same camera for both paths: its TCP stream and its Zenoh endpoint on the
    // shaped link, each guarded as anything beyond loopback must be.
    let config = session_config(
        args,
        scene,
        &format!("{HOST_IP}:0"),
        Some(&secret),
        &format!("tcp/{HOST_IP}:0"),
        Some(&users),
    )?;
    let shutdown = CancellationToken::new();
    let session = start_session(config, shutdown.clone()).await?;
    let _stop = shutdown.clone().drop_guard();
    let (added, before_tap) = tap(&session.hub)?;
    let connect = match via {
        Via::Tcp => session
            .local_addr
            .context("the session does not serve")?
            .to_string(),
        Via::Zenoh => session
            .zenoh_locators
            .first()
            .cloned()
            .context("the session publishes on no Zenoh endpoint")?,
    };
    let exe = std::env::current_exe()?;
    let mut command = Command::new("ip");
    command
        .args(["netns", "exec", &net.name])
        .arg(&exe)
        .args(["zenoh", "--viewer-only", "--via", via.arg()])
        .args(["--connect", &connect])
        .arg("--secret-file")
        .arg(&secret_file)
        .args(["--frames", &args.frames.to_string()])
        .args(["--timeout-s", &args.timeout_s.to_string()]);
    if let Some(n) = args.viewer_in_flight {
        command.args(["--viewer-in-flight", &n.to_string()]);
    }
    if let Some(t) = args.query_timeout_s {
        command.args(["--query-timeout-s", &t.to_string()]);
    }
    let tx_before = net.host_tx_bytes();
    let mut child = ChildGuard(
        command
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .context("starting the viewer in the namespace")?,
    );
    let started = Instant::now();
    tokio::time::timeout(Duration::from_secs(120), session.sources_done.cancelled())
        .await
        .context("the camera did not finish within 120 s")?;
    let camera_done_ns = now_ns();
    eprintln!(
        "zenoh: the camera finished {:.1} s after the viewer started; waiting for the viewer",
        started.elapsed().as_secs_f64()
    );
    let limit = Duration::from_secs(args.timeout_s + 60);
    let status = loop {
        if let Some(status) = child.0.try_wait()? {
            break status;
        }
        if started.elapsed() > limit {
            bail!("the viewer in the namespace did not end within {limit:?}");
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    let mut stdout = String::new();
    if let Some(mut s) = child.0.stdout.take() {
        s.read_to_string(&mut stdout)?;
    }
    if !status.success() {
        bail!("the viewer in the namespace failed ({status}): {stdout}");
    }
    let viewing: Viewing = serde_json::from_str(&stdout)
        .with_context(|| format!("the viewer in the namespace said: {stdout}"))?;
    let host_tx_bytes = net
        .host_tx_bytes()
        .zip(tx_before)
        .map(|(after, before)| after.saturating_sub(before));
    shutdown.cancel();
    let summary = session.wait().await?;
    let camera = Camera {
        added: taken(&added),
        before_tap,
        status: summary.status,
    };
    let camera_done_s = secs(camera_done_ns.saturating_sub(camera.first_added_ns()));
    Ok(Shaped {
        via,
        camera,
        viewing,
        host_tx_bytes,
        camera_done_s,
    })
}

/// `--viewer-only`: follows the camera at `--connect` on `--via` and prints what it
/// got (JSON) on stdout.
pub(super) fn viewer_only(args: &Args) -> Result<()> {
    let connect = args.connect.as_deref().context("--connect is needed")?;
    let secret = match &args.secret_file {
        Some(file) => {
            let text = std::fs::read_to_string(file)
                .with_context(|| format!("--secret-file {}", file.display()))?;
            Some(text.lines().next().unwrap_or("").trim_end().to_string())
        }
        None => None,
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let opts = ViewOptions::of(args);
    let viewing = runtime.block_on(async {
        match args.via {
            Via::Tcp => view_tcp(connect, secret.as_deref().unwrap_or(""), &opts).await,
            Via::Zenoh => view_zenoh(connect, secret.as_deref(), &opts).await,
        }
    })?;
    println!("{}", serde_json::to_string(&viewing)?);
    Ok(())
}

pub(super) fn shaped_report(
    out: &mut String,
    args: &Args,
    shaped: &[Shaped],
    qdisc: &str,
    tcp: &[&Run],
    zenoh: &[&Run],
) {
    let mut w = |line: String| {
        let _ = writeln!(out, "{line}");
    };
    w(format!(
        "\n## Through a rate-limited link ({} kbit/s)\n",
        args.rate_kbit
    ));
    w(format!(
        "A network namespace joined by a veth pair, the daemon's end ({HOST_IP}) shaped \
         with `tc qdisc ... tbf rate {}kbit burst 32kbit latency 400ms` (daemon to viewer; \
         the requests back are not shaped). The same camera serves its TCP stream (with a \
         token) and publishes on Zenoh (user/password authentication) there; a live \
         viewer in the namespace ({VIEWER_IP}; this binary with --viewer-only, the same \
         client{}) starts before the first scan; the daemon's runtime has {} worker \
         threads. Runs interleaved TCP, Zenoh, ... ({} of \
         each).\n",
        args.rate_kbit,
        match (args.viewer_in_flight, args.query_timeout_s) {
            (None, None) => " and gateway settings as on loopback".to_string(),
            (n, t) => format!(
                ", {} requests outstanding, gateway query timeout {}",
                n.map_or("16".into(), |n| n.to_string()),
                t.map_or("10 s".into(), |t| format!("{t} s"))
            ),
        },
        daemon_workers(args),
        args.shaped_repeats
    ));
    w(
        "| run | path | scans at the viewer / added by the camera | unavailable | whole model \
         after the first scan (s) | latency p50 / p99 (s) | link MB received | mean rate \
         (kbit/s) | shaped end sent (MB) |"
            .into(),
    );
    w("|---|---|---|---|---|---|---|---|---|".into());
    for (via, rs) in [(Via::Tcp, tcp), (Via::Zenoh, zenoh)] {
        if rs.is_empty() {
            continue;
        }
        let whole = median(rs.iter().map(|r| r.live_whole_s()));
        let bytes = median(rs.iter().map(|r| r.live.link_bytes as f64));
        w(format!(
            "| loopback (medians above) | {} | {} / {} | 0 | {whole:.2} | {:.3} / {:.3} | {:.2} \
             | {:.0} | — |",
            via.name(),
            median(rs.iter().map(|r| r.live.arrivals.len() as f64)),
            median(rs.iter().map(|r| r.camera.added.len() as f64)),
            median(rs.iter().map(|r| r.latency().0)) / 1e3,
            median(rs.iter().map(|r| r.latency().1)) / 1e3,
            bytes / 1e6,
            bytes * 8e-3 / whole.max(1e-9)
        ));
    }
    for (i, s) in shaped.iter().enumerate() {
        let v = &s.viewing;
        let (p50, p99) = percentiles(&latencies_ms(&s.camera, v).0);
        let span = secs(
            v.last_arrival_ns()
                .saturating_sub(s.camera.first_added_ns()),
        );
        w(format!(
            "| {} | {} | {} / {} | {} | {} | {:.1} / {:.1} | {:.2} | {:.0} | {} |",
            i + 1,
            s.via.name(),
            v.arrivals.len(),
            s.camera.added.len(),
            v.unavailable.len(),
            s.whole_s()
                .map_or("never".to_string(), |t| format!("{t:.1}")),
            p50 / 1e3,
            p99 / 1e3,
            v.link_bytes as f64 / 1e6,
            v.link_bytes as f64 * 8e-3 / span.max(1e-9),
            s.host_tx_bytes
                .map_or("n/a".into(), |b| format!("{:.2}", b as f64 / 1e6)),
        ));
    }
    w(format!("\ntbf on the shaped end over all runs: {qdisc}"));
    for (i, s) in shaped.iter().enumerate() {
        let v = &s.viewing;
        let early = latencies_ms(&s.camera, v).1 + s.camera.before_tap;
        let mut notes = vec![format!(
            "viewer ready {:.2} s after it started, {early} scans added before that",
            secs(v.ready_ns.saturating_sub(v.started_ns))
        )];
        if !v.unavailable.is_empty() {
            let reasons: BTreeSet<String> = v
                .unavailable
                .values()
                .map(|r| {
                    // "... did not answer for scan 12": one reason, whatever the id.
                    r.trim_end_matches(|c: char| c.is_ascii_digit())
                        .trim_end()
                        .to_string()
                })
                .collect();
            notes.push(format!(
                "unavailable: {}",
                reasons.into_iter().collect::<Vec<_>>().join("; ")
            ));
        }
        if v.unanswered > 0 {
            notes.push(format!("{} requests never answered", v.unanswered));
        }
        w(format!(
            "- run {} ({}): {}",
            i + 1,
            s.via.name(),
            notes.join("; ")
        ));
    }
    w("\nThe camera in the same runs:\n".into());
    camera_header(&mut w);
    for (name, rs) in [
        ("loopback, TCP viewer (medians)", tcp),
        ("loopback, Zenoh viewer (medians)", zenoh),
    ] {
        if rs.is_empty() {
            continue;
        }
        let cams: Vec<&Camera> = rs.iter().map(|r| &r.camera).collect();
        w(camera_row(name, &cams));
    }
    for (i, s) in shaped.iter().enumerate() {
        w(camera_row(
            &format!(
                "run {}: {} kbit/s, {} viewer (sources ended {:.2} s after the first scan)",
                i + 1,
                args.rate_kbit,
                s.via.name(),
                s.camera_done_s
            ),
            &[&s.camera],
        ));
    }
}
