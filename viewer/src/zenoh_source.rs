//! `--zenoh`: the cameras a key pattern names on Zenoh, merged by the gateway
//! (`texel_client::zenoh_gateway`) into one stream on a loopback port that the
//! viewer then follows like a daemon. Native only.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use texel_client::zenoh_gateway::{Gateway, GatewayOptions};

/// Where to find cameras on Zenoh.
#[derive(Args, Clone, Debug)]
pub struct ZenohArgs {
    /// Follow the cameras on Zenoh (`texel/<site>/<camera>`) instead of one daemon.
    #[arg(long)]
    pub zenoh: bool,
    /// Which sites (`*`: all).
    #[arg(long, default_value = "*", requires = "zenoh")]
    pub site: String,
    /// Which cameras: a name, or a pattern with `*` (`*`: all).
    #[arg(long, default_value = "*", requires = "zenoh")]
    pub camera: String,
    /// A Zenoh endpoint to connect to (`tcp/HOST:PORT`: a camera or a router);
    /// repeatable. None: find peers by multicast scouting.
    #[arg(long = "zenoh-connect", value_name = "ENDPOINT", requires = "zenoh")]
    pub zenoh_connect: Vec<String>,
    /// Join as a Zenoh client of the routers in `--zenoh-connect` (default: peer).
    #[arg(long = "zenoh-client", requires = "zenoh")]
    pub zenoh_client: bool,
    /// Zenoh user/password authentication: who this viewer is.
    #[arg(long = "zenoh-user", requires = "zenoh_password_file")]
    pub zenoh_user: Option<String>,
    /// A file whose first line is the password of `--zenoh-user`.
    #[arg(long = "zenoh-password-file", requires = "zenoh_user")]
    pub zenoh_password_file: Option<PathBuf>,
}

/// A gateway and the runtime its tasks run on; the viewer connects to `addr`.
pub struct ZenohSource {
    pub addr: String,
    _gateway: Gateway,
    _runtime: tokio::runtime::Runtime,
}

impl ZenohArgs {
    /// The Zenoh config these options make.
    pub fn zenoh_config(&self) -> anyhow::Result<zenoh::Config> {
        let mut config = zenoh::Config::default();
        let mut set = |key: &str, value: String| {
            config
                .insert_json5(key, &value)
                .map_err(|e| anyhow::anyhow!("zenoh config {key}: {e}"))
        };
        let json = |v: serde_json::Value| v.to_string();
        set(
            "mode",
            json(if self.zenoh_client { "client" } else { "peer" }.into()),
        )?;
        // A viewer listens on nothing: it only connects.
        set("listen/endpoints", "[]".into())?;
        set("connect/endpoints", json(self.zenoh_connect.clone().into()))?;
        set(
            "scouting/multicast/enabled",
            self.zenoh_connect.is_empty().to_string(),
        )?;
        if let (Some(user), Some(file)) = (&self.zenoh_user, &self.zenoh_password_file) {
            let text = std::fs::read_to_string(file)
                .with_context(|| format!("--zenoh-password-file {}", file.display()))?;
            let password = text.lines().next().unwrap_or("").trim_end();
            if password.is_empty() {
                anyhow::bail!(
                    "--zenoh-password-file {}: its first line is empty",
                    file.display()
                );
            }
            set("transport/auth/usrpwd/user", json(user.clone().into()))?;
            set("transport/auth/usrpwd/password", json(password.into()))?;
        }
        Ok(config)
    }

    /// Starts the gateway on a runtime of its own.
    pub fn start(&self) -> anyhow::Result<ZenohSource> {
        init_gateway_logging();
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .thread_name("zenoh-gateway")
            .build()
            .context("starting the Zenoh gateway's runtime")?;
        let options = GatewayOptions::new(&self.site, &self.camera, self.zenoh_config()?);
        let gateway = runtime
            .block_on(Gateway::start(options))
            .context("starting the Zenoh gateway")?;
        let addr = gateway.addr.to_string();
        eprintln!(
            "texel-viewer: following texel/{}/{} on Zenoh{}",
            self.site,
            self.camera,
            if self.zenoh_connect.is_empty() {
                " (multicast scouting)".to_string()
            } else {
                format!(" via {}", self.zenoh_connect.join(", "))
            }
        );
        Ok(ZenohSource {
            addr,
            _gateway: gateway,
            _runtime: runtime,
        })
    }
}

/// Zenoh's own crates, quieted below errors unless `RUST_LOG` names them: their
/// warnings (a scouting delay, a query timing out and asked again) are the gateway's
/// business, not the user's.
const QUIET_ZENOH: &str =
    "zenoh=error,zenoh_transport=error,zenoh_link_tcp=error,zenoh_config=error";

/// Shows the gateway's warnings on stderr (a camera in another world frame, a camera
/// that does not answer); `RUST_LOG` overrides the default `warn`.
fn init_gateway_logging() {
    let directives = match std::env::var("RUST_LOG") {
        Ok(v) if v.contains("zenoh") => v,
        Ok(v) if !v.trim().is_empty() => format!("{v},{QUIET_ZENOH}"),
        _ => format!("warn,{QUIET_ZENOH}"),
    };
    let filter = tracing_subscriber::EnvFilter::try_new(&directives)
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(format!("warn,{QUIET_ZENOH}")));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}
