//! The bench's viewers: a `texel_client::Client` on the daemon's TCP stream or on a
//! Zenoh gateway's port, reading until the whole model is here, and the bytes the
//! kernel received on its link (`ss`).

use super::*;

/// What one viewer got.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub(super) struct Viewing {
    /// When it started connecting (Unix ns).
    pub(super) started_ns: u64,
    /// When it could receive: connected, and for Zenoh the camera's listing in.
    pub(super) ready_ns: u64,
    /// The camera's own scan id -> when its data reached the client (Unix ns).
    pub(super) arrivals: BTreeMap<u64, u64>,
    /// Scans the server said it cannot send (the client does not ask again).
    pub(super) unavailable: BTreeMap<u64, String>,
    /// Bytes the kernel received on the viewer's link(s) from the daemon.
    pub(super) link_bytes: u64,
    /// Scans listed to the client.
    pub(super) listed: usize,
    /// Requests outstanding at the end.
    pub(super) unanswered: usize,
    /// Whether every scan arrived before the deadline.
    pub(super) complete: bool,
}

impl Viewing {
    pub(super) fn last_arrival_ns(&self) -> u64 {
        self.arrivals
            .values()
            .copied()
            .max()
            .unwrap_or(self.ready_ns)
    }

    /// Connect to the whole model (s).
    pub(super) fn whole_model_s(&self) -> f64 {
        secs(self.last_arrival_ns().saturating_sub(self.started_ns))
    }
}

/// How a viewer reads.
#[derive(Debug, Clone, Copy)]
pub(super) struct ViewOptions {
    pub(super) frames: usize,
    pub(super) deadline: Duration,
    pub(super) in_flight: Option<usize>,
    pub(super) query_timeout: Option<Duration>,
}

impl ViewOptions {
    pub(super) fn of(args: &Args) -> Self {
        Self {
            frames: args.frames,
            deadline: Duration::from_secs(args.timeout_s),
            in_flight: args.viewer_in_flight,
            query_timeout: args.query_timeout_s.map(Duration::from_secs_f64),
        }
    }
}

/// A viewer on the daemon's TCP stream at `addr`.
pub(super) async fn view_tcp(addr: &str, token: &str, opts: &ViewOptions) -> Result<Viewing> {
    let addr: std::net::SocketAddr = addr.parse().with_context(|| format!("address {addr:?}"))?;
    let before = link_sockets(addr.port())?;
    let started_ns = now_ns();
    let mut client = Client::connect(addr, token, "texel-bench zenoh").await?;
    if let Some(n) = opts.in_flight {
        client.set_max_in_flight(n);
    }
    let ready_ns = now_ns();
    let mut v = read_whole_model(&mut client, opts, |id| id, opts.deadline, &String::new).await?;
    v.started_ns = started_ns;
    v.ready_ns = ready_ns;
    v.link_bytes = new_link_bytes(addr.port(), &before)?;
    client.close().await;
    Ok(v)
}

/// A viewer through a Zenoh gateway connected to `endpoint`.
pub(super) async fn view_zenoh(
    endpoint: &str,
    password: Option<&str>,
    opts: &ViewOptions,
) -> Result<Viewing> {
    let port = endpoint_port(endpoint)?;
    let before = link_sockets(port)?;
    let started_ns = now_ns();
    let mut options = GatewayOptions::new(SITE, CAMERA, gateway_config(endpoint, password)?);
    if let Some(t) = opts.query_timeout {
        options.query_timeout = t;
    }
    let gateway = Gateway::start(options).await?;
    let mut client = Client::connect(gateway.addr, "", "texel-bench zenoh").await?;
    if let Some(n) = opts.in_flight {
        client.set_max_in_flight(n);
    }
    let listed = Instant::now();
    while !gateway.cameras().iter().any(|c| c.listing_received) {
        if listed.elapsed() > opts.deadline {
            bail!(
                "the camera's listing did not arrive within {:?}",
                opts.deadline
            );
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    let ready_ns = now_ns();
    let left = opts
        .deadline
        .saturating_sub(Duration::from_nanos(ready_ns.saturating_sub(started_ns)));
    let describe = || -> String {
        gateway
            .cameras()
            .iter()
            .map(|c| {
                format!(
                    "; {}: alive {}, listing in {}, {} scans listed",
                    c.prefix, c.alive, c.listing_received, c.scans
                )
            })
            .collect()
    };
    let mut v = read_whole_model(&mut client, opts, |g| split_id(g).1, left, &describe).await?;
    v.started_ns = started_ns;
    v.ready_ns = ready_ns;
    v.link_bytes = new_link_bytes(port, &before)?;
    client.close().await;
    drop(gateway);
    Ok(v)
}

/// A viewer's Zenoh config: a peer that listens on nothing, connects to `endpoint`
/// and does not scout (as `texel-viewer --zenoh --zenoh-connect` makes it).
pub(super) fn gateway_config(endpoint: &str, password: Option<&str>) -> Result<zenoh::Config> {
    let mut config = zenoh::Config::default();
    let mut set = |key: &str, value: String| {
        config
            .insert_json5(key, &value)
            .map_err(|e| anyhow!("zenoh config {key}: {e}"))
    };
    let json = |v: serde_json::Value| v.to_string();
    set("mode", json("peer".into()))?;
    set("listen/endpoints", "[]".into())?;
    set("connect/endpoints", json(vec![endpoint.to_string()].into()))?;
    set("scouting/multicast/enabled", "false".into())?;
    if let Some(password) = password {
        set("transport/auth/usrpwd/user", json(VIEWER_USER.into()))?;
        set("transport/auth/usrpwd/password", json(password.into()))?;
    }
    Ok(config)
}

/// Reads until every one of `frames` scans is here, or, when fewer were listed
/// (the camera skipped frames), every listed scan is here or unavailable and nothing
/// has changed for [`QUIET`], or `deadline` passed. `own` maps a served id to the
/// camera's own.
pub(super) async fn read_whole_model(
    client: &mut Client,
    opts: &ViewOptions,
    own: impl Fn(u64) -> u64,
    deadline: Duration,
    describe: &dyn Fn() -> String,
) -> Result<Viewing> {
    let frames = opts.frames;
    let end = Instant::now() + deadline;
    let mut v = Viewing::default();
    let mut listed = BTreeSet::new();
    let mut said = Instant::now();
    let mut changed = Instant::now();
    loop {
        let settled = v.arrivals.len() + v.unavailable.len() >= listed.len();
        if v.arrivals.len() >= frames
            || (settled && !listed.is_empty() && changed.elapsed() > QUIET)
        {
            break;
        }
        if said.elapsed() > PROGRESS {
            said = Instant::now();
            eprintln!(
                "  viewer: {} listed, {} of {frames} scans here, {} unavailable, {} requests \
                 unanswered{}",
                listed.len(),
                v.arrivals.len(),
                v.unavailable.len(),
                client.fetch_plan().in_flight(),
                describe()
            );
        }
        let left = end.saturating_duration_since(Instant::now()).min(PROGRESS);
        if left.is_zero() {
            break;
        }
        let Ok(message) = tokio::time::timeout(left, client.next_message()).await else {
            continue;
        };
        match message? {
            Some(Message::ScanListed { id, .. }) => {
                changed = Instant::now();
                listed.insert(own(id));
            }
            Some(Message::ScanAdded(scan)) => {
                let at = now_ns();
                changed = Instant::now();
                // The TCP stream sends a new scan's data without listing it first.
                listed.insert(own(scan.id));
                v.unavailable.remove(&own(scan.id));
                v.arrivals.entry(own(scan.id)).or_insert(at);
            }
            Some(Message::ScanUnavailable { id, reason }) => {
                changed = Instant::now();
                v.unavailable.insert(own(id), reason);
            }
            Some(Message::Goodbye { reason }) => bail!("the server said goodbye: {reason}"),
            None => bail!("the server closed the connection"),
            Some(_) => {}
        }
    }
    v.listed = listed.len();
    v.unanswered = client.fetch_plan().in_flight();
    v.complete = v.arrivals.len() >= frames;
    Ok(v)
}

/// How often a slow viewer says how far it got.
pub(super) const PROGRESS: Duration = Duration::from_secs(10);
/// How long a viewer that has every listed scan (or was told it cannot have it)
/// waits for more before it ends.
pub(super) const QUIET: Duration = Duration::from_secs(15);

pub(super) fn endpoint_port(endpoint: &str) -> Result<u16> {
    endpoint
        .rsplit_once(':')
        .and_then(|(_, p)| p.parse().ok())
        .with_context(|| format!("no port in {endpoint:?}"))
}

/// Established TCP sockets whose peer port is `port`: local address -> bytes
/// received (`ss`, the kernel's `tcp_info`).
pub(super) fn link_sockets(port: u16) -> Result<BTreeMap<String, u64>> {
    let out = Command::new("ss")
        .args([
            "-tinHO",
            "state",
            "established",
            "dport",
            "=",
            &format!(":{port}"),
        ])
        .output()
        .context("running ss (iproute2)")?;
    if !out.status.success() {
        bail!("ss: {}", String::from_utf8_lossy(&out.stderr));
    }
    let mut sockets = BTreeMap::new();
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        let fields: Vec<&str> = line.split_whitespace().collect();
        let Some(local) = fields.get(2) else { continue };
        let received = fields
            .iter()
            .find_map(|f| f.strip_prefix("bytes_received:"))
            .and_then(|n| n.parse().ok())
            .unwrap_or(0);
        sockets.insert((*local).to_string(), received);
    }
    Ok(sockets)
}

/// Bytes received on the sockets to `port` opened since `before`.
pub(super) fn new_link_bytes(port: u16, before: &BTreeMap<String, u64>) -> Result<u64> {
    Ok(link_sockets(port)?
        .into_iter()
        .filter(|(local, _)| !before.contains_key(local))
        .map(|(_, bytes)| bytes)
        .sum())
}
