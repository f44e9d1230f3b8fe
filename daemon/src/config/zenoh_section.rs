//! The `[zenoh]` section: publishing the model on Zenoh (`docs/daemon.md`, "On
//! Zenoh"): the camera's keys, the Zenoh mode and endpoints, and the access control
//! that any endpoint beyond loopback requires.

use std::path::PathBuf;

use serde::Deserialize;

/// How the daemon joins Zenoh.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ZenohMode {
    /// Talks to other peers directly (no router needed on one network).
    Peer,
    /// Talks only through the routers in `connect` (wider deployments).
    Client,
}

impl ZenohMode {
    pub fn name(self) -> &'static str {
        match self {
            Self::Peer => "peer",
            Self::Client => "client",
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ZenohSection {
    /// Publish the model on Zenoh.
    pub enabled: bool,
    /// The `<site>` chunk of every key.
    pub site: String,
    /// The `<camera>` chunk of every key. Default: the session's name.
    pub camera: Option<String>,
    pub mode: ZenohMode,
    /// Zenoh endpoints to listen on (`tcp/HOST:PORT`).
    pub listen: Vec<String>,
    /// Zenoh endpoints to connect to (other peers, or routers in client mode).
    pub connect: Vec<String>,
    /// Find peers by UDP multicast (announces this daemon beyond loopback: needs
    /// `[zenoh.auth]`).
    pub multicast_scouting: bool,
    /// The name of the frame this camera's poses are in. Cameras publishing the same
    /// name are drawn overlaid; others each in its own frame. Default: `sim:<scene
    /// file stem>` for a simulated camera (its world is the scene's truth frame), else
    /// `<site>/<camera>` (its own first scan).
    pub world_frame: Option<String>,
    pub auth: ZenohAuth,
    /// A JSON5 file holding Zenoh's `access_control` section (rules per key
    /// expression and subject), passed to Zenoh as it is.
    pub access_control: Option<PathBuf>,
}

impl Default for ZenohSection {
    fn default() -> Self {
        Self {
            enabled: false,
            site: "site".into(),
            camera: None,
            mode: ZenohMode::Peer,
            listen: vec!["tcp/127.0.0.1:0".into()],
            connect: Vec::new(),
            multicast_scouting: false,
            world_frame: None,
            auth: ZenohAuth::default(),
            access_control: None,
        }
    }
}

/// `[zenoh.auth]`: Zenoh's user/password authentication.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ZenohAuth {
    /// Who this daemon is to the peers and routers it connects to.
    pub user: Option<String>,
    /// A file holding this daemon's password (first line), so the session file
    /// holds no secret.
    pub password_file: Option<PathBuf>,
    /// `user:password` lines: who may connect to this daemon.
    pub dictionary_file: Option<PathBuf>,
}

impl ZenohAuth {
    /// Whether anyone connecting to this daemon must authenticate.
    pub fn guards_endpoints(&self) -> bool {
        self.dictionary_file.is_some()
    }
}

impl ZenohSection {
    /// The camera chunk: `camera`, else the session's name.
    pub fn camera_name(&self, session_name: &str) -> String {
        self.camera
            .clone()
            .unwrap_or_else(|| session_name.to_string())
    }

    /// Checks what can be checked without opening Zenoh; `Err((key, message))`.
    pub fn validate(&self, session_name: &str) -> Result<(), (&'static str, String)> {
        if !self.enabled {
            return Ok(());
        }
        texel::wire::zenoh_keys::check_chunk("site", &self.site)
            .map_err(|e| ("zenoh.site", e.to_string()))?;
        texel::wire::zenoh_keys::check_chunk("camera", &self.camera_name(session_name)).map_err(
            |e| {
                (
                    "zenoh.camera",
                    format!("{e} (unset, it is the session's name)"),
                )
            },
        )?;
        for (key, endpoints) in [
            ("zenoh.listen", &self.listen),
            ("zenoh.connect", &self.connect),
        ] {
            for e in endpoints.iter() {
                endpoint_host(e).map_err(|m| (key, format!("{e:?}: {m}")))?;
            }
        }
        if self.mode == ZenohMode::Client && self.connect.is_empty() {
            return Err((
                "zenoh.connect",
                "client mode needs a router to connect to".into(),
            ));
        }
        if self.mode == ZenohMode::Client && !self.listen.is_empty() {
            return Err((
                "zenoh.listen",
                "a client listens on nothing: set listen = [] or mode = \"peer\"".into(),
            ));
        }
        let open: Vec<&String> = self
            .listen
            .iter()
            .filter(|e| !endpoint_is_loopback(e))
            .collect();
        if !self.auth.guards_endpoints() {
            if let Some(e) = open.first() {
                return Err((
                    "zenoh.listen",
                    format!(
                        "{e:?} is open beyond loopback: set [zenoh.auth] dictionary_file \
                         (who may connect) first"
                    ),
                ));
            }
            if self.multicast_scouting {
                return Err((
                    "zenoh.multicast_scouting",
                    "announces the daemon beyond loopback: set [zenoh.auth] \
                     dictionary_file (who may connect) first"
                        .into(),
                ));
            }
        }
        if self.auth.user.is_some() != self.auth.password_file.is_some() {
            return Err((
                "zenoh.auth.user",
                "user and password_file go together".into(),
            ));
        }
        if let Some(frame) = &self.world_frame
            && (frame.is_empty() || frame.len() > 256)
        {
            return Err(("zenoh.world_frame", "must be 1 to 256 bytes".into()));
        }
        Ok(())
    }
}

/// The host of a `tcp/HOST:PORT` endpoint (Zenoh's locator syntax; only TCP is
/// built in).
fn endpoint_host(endpoint: &str) -> Result<&str, String> {
    let rest = endpoint
        .strip_prefix("tcp/")
        .ok_or_else(|| "only tcp/HOST:PORT endpoints are built in".to_string())?;
    // Zenoh appends `#` config and `?` metadata; the address ends before them.
    let addr = rest.split(['#', '?']).next().unwrap_or(rest);
    let (host, port) = addr
        .rsplit_once(':')
        .ok_or_else(|| "no :PORT".to_string())?;
    port.parse::<u16>()
        .map_err(|_| format!("port {port:?} is not a number in 0..=65535"))?;
    let host = host.trim_start_matches('[').trim_end_matches(']');
    if host.is_empty() {
        return Err("no host".into());
    }
    Ok(host)
}

/// Whether an endpoint listens on loopback only.
pub fn endpoint_is_loopback(endpoint: &str) -> bool {
    match endpoint_host(endpoint) {
        Ok("localhost") => true,
        Ok(host) => host
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback()),
        Err(_) => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn on() -> ZenohSection {
        ZenohSection {
            enabled: true,
            ..ZenohSection::default()
        }
    }

    #[test]
    fn defaults_are_loopback_and_valid() {
        assert!(on().validate("texel").is_ok());
        assert!(endpoint_is_loopback("tcp/127.0.0.1:0"));
        assert!(endpoint_is_loopback("tcp/[::1]:7447"));
        assert!(endpoint_is_loopback("tcp/localhost:7447"));
        assert!(!endpoint_is_loopback("tcp/0.0.0.0:7447"));
        assert!(!endpoint_is_loopback("tcp/10.1.2.3:7447"));
    }

    #[test]
    fn open_endpoints_need_authentication() {
        let mut c = on();
        c.listen = vec!["tcp/0.0.0.0:7447".into()];
        let (key, message) = c.validate("texel").unwrap_err();
        assert_eq!(key, "zenoh.listen");
        assert!(message.contains("dictionary_file"), "{message}");
        c.auth.dictionary_file = Some("users.txt".into());
        assert!(c.validate("texel").is_ok());

        let mut c = on();
        c.multicast_scouting = true;
        assert_eq!(
            c.validate("texel").unwrap_err().0,
            "zenoh.multicast_scouting"
        );
    }

    #[test]
    fn bad_names_endpoints_and_modes_are_named() {
        let mut c = on();
        c.camera = Some("a/b".into());
        assert_eq!(c.validate("texel").unwrap_err().0, "zenoh.camera");
        let c = on();
        assert_eq!(c.validate("my session").unwrap_err().0, "zenoh.camera");
        let mut c = on();
        c.connect = vec!["udp/1.2.3.4:7447".into()];
        assert_eq!(c.validate("texel").unwrap_err().0, "zenoh.connect");
        c.connect = vec!["tcp/1.2.3.4:port".into()];
        assert_eq!(c.validate("texel").unwrap_err().0, "zenoh.connect");
        let mut c = on();
        c.mode = ZenohMode::Client;
        assert_eq!(c.validate("texel").unwrap_err().0, "zenoh.connect");
        c.connect = vec!["tcp/10.0.0.1:7447".into()];
        assert_eq!(c.validate("texel").unwrap_err().0, "zenoh.listen");
        c.listen.clear();
        assert!(c.validate("texel").is_ok());
        let mut c = on();
        c.auth.user = Some("cam".into());
        assert_eq!(c.validate("texel").unwrap_err().0, "zenoh.auth.user");
    }
}
