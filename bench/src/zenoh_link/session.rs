//! The bench's camera: an in-process daemon on the simulator whose scans are placed
//! at the true poses, a tap timestamping each scan the hub adds, and the camera's
//! figures (counters, stage latencies) as rows of the reports.

use super::*;

/// The camera's side of a run.
#[derive(Debug, Clone, Default)]
pub(super) struct Camera {
    /// Scan id -> when the hub added it (Unix ns).
    pub(super) added: BTreeMap<u64, u64>,
    /// Scans the hub held before the run's own subscription began (none expected:
    /// frames are rendered first).
    pub(super) before_tap: usize,
    pub(super) status: texel::wire::Status,
}

impl Camera {
    pub(super) fn first_added_ns(&self) -> u64 {
        self.added.values().copied().min().unwrap_or(0)
    }

    /// First to last scan added (s): the camera's own pace.
    pub(super) fn span_s(&self) -> f64 {
        let last = self.added.values().copied().max().unwrap_or(0);
        secs(last.saturating_sub(self.first_added_ns()))
    }

    pub(super) fn counter(&self, name: &str) -> u64 {
        self.status.counters.get(name).copied().unwrap_or(0)
    }

    pub(super) fn stage(&self, name: &str) -> (f64, f64) {
        self.status
            .stages
            .iter()
            .find(|s| s.stage == name)
            .map_or((f64::NAN, f64::NAN), |s| (s.p50_ms, s.p99_ms))
    }
}

/// The session: the simulated camera, serving its TCP stream at `bind` (with
/// `token` when given) and publishing on Zenoh at `listen` (with `dictionary`
/// guarding it when given).
pub(super) fn session_config(
    args: &Args,
    scene: &Path,
    bind: &str,
    token: Option<&str>,
    listen: &str,
    dictionary: Option<&Path>,
) -> Result<SessionConfig> {
    let auth = dictionary.map_or(String::new(), |d| {
        format!("[zenoh.auth]\ndictionary_file = {d:?}\n")
    });
    let token = token.map_or(String::new(), |t| format!("token = {t:?}\n"));
    let toml = format!(
        "[session]\nname = \"bench-zenoh\"\nexit_when_sources_end = false\n\
         [[source.sim]]\nscene = {scene:?}\nseed = 1\nframes = {}\nspeed = 1.0\n\
         prerender = true\nlate = \"wait\"\ntruth = true\n\
         [pipeline]\noverload = \"keep-newest\"\n\
         [serve]\nbind = \"{bind}\"\nweb = false\n{token}\
         [status]\nlog = false\n\
         [model.retirement]\nenabled = false\n\
         [zenoh]\nenabled = true\nsite = \"{SITE}\"\ncamera = \"{CAMERA}\"\n\
         listen = [\"{listen}\"]\nmulticast_scouting = false\n{auth}",
        args.frames
    );
    Ok(SessionConfig::from_toml_str(&toml, "texel-bench zenoh")?)
}

/// Starts a session whose scans are placed at the simulator's true poses: the
/// camera's cost without registration's, the same in every run.
pub(super) async fn start_session(
    config: SessionConfig,
    shutdown: CancellationToken,
) -> Result<Session> {
    let stage = Box::new(TruthPlacement { next_id: 0 });
    Ok(Session::start_with_registration(config, stage, shutdown).await?)
}

/// Places each scan at the true pose its source sent.
pub(super) struct TruthPlacement {
    pub(super) next_id: u64,
}

impl Registration for TruthPlacement {
    fn name(&self) -> &str {
        "truth"
    }

    fn register(&mut self, scan: &Arc<TexelScan>, input: ScanInput<'_>) -> StageOutput {
        let (placement, events) = match input.truth {
            Some(world_from_scan) => {
                let id = self.next_id;
                self.next_id += 1;
                (
                    Placement::Placed {
                        id,
                        degenerate: false,
                    },
                    vec![ModelEvent::ScanAdded {
                        id,
                        scan: Arc::clone(scan),
                        world_from_scan,
                    }],
                )
            }
            None => (
                Placement::Failed(PlacementFailure {
                    kind: "no-pose",
                    reason: "no true pose".into(),
                }),
                Vec::new(),
            ),
        };
        StageOutput {
            placement,
            events,
            recovered: 0,
            anchors: Vec::new(),
        }
    }
}

/// Scan id -> when the hub added it (Unix ns), filled as scans come.
pub(super) type Added = Arc<Mutex<BTreeMap<u64, u64>>>;

/// Timestamps every scan the hub adds, from a subscription of its own.
pub(super) fn tap(hub: &Arc<Hub>) -> Result<(Added, usize)> {
    let mut sub = hub.subscribe_version(2)?;
    let before = sub.snapshot.len().saturating_sub(2);
    let added = Arc::new(Mutex::new(BTreeMap::new()));
    let a = Arc::clone(&added);
    tokio::spawn(async move {
        while let Some(frame) = sub.live.recv().await {
            if let Some((kind::SCAN_ADDED, Some(id))) = frame_head(&frame) {
                let at = now_ns();
                a.lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .entry(id)
                    .or_insert(at);
            }
        }
    });
    Ok((added, before))
}

pub(super) fn taken(added: &Mutex<BTreeMap<u64, u64>>) -> BTreeMap<u64, u64> {
    added.lock().unwrap_or_else(PoisonError::into_inner).clone()
}

pub(super) fn camera_header(w: &mut impl FnMut(String)) {
    w(
        "| camera | scans added | paired | skipped by overload | late range / EO | \
         end-to-end stage p50 / p99 (ms) | encode p50 / p99 (ms) | first to last scan added (s) |"
            .into(),
    );
    w("|---|---|---|---|---|---|---|---|".into());
}

pub(super) fn camera_row(name: &str, cams: &[&Camera]) -> String {
    let m = |f: &dyn Fn(&Camera) -> f64| median(cams.iter().map(|c| f(c)));
    let count = |n: &'static str| move |cam: &Camera| cam.counter(n) as f64;
    format!(
        "| {name} | {:.0} | {:.0} | {:.0} | {:.0} / {:.0} | {:.1} / {:.1} | {:.1} / {:.1} | {:.2} |",
        m(&|c| c.added.len() as f64),
        m(&count("paired")),
        m(&count("skipped_by_overload")),
        m(&count("late_range")),
        m(&count("late_eo")),
        m(&|c| c.stage("end_to_end").0),
        m(&|c| c.stage("end_to_end").1),
        m(&|c| c.stage("encode").0),
        m(&|c| c.stage("encode").1),
        m(&|c| c.span_s()),
    )
}
