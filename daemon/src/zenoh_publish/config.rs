//! The Zenoh configuration a `[zenoh]` section makes: mode, endpoints, scouting,
//! user/password authentication and access control, everything else Zenoh's
//! defaults.

use crate::config::{ZenohMode, ZenohSection};

use super::ZenohError;

/// How long (µs) a blocking put may wait for the link before Zenoh closes the
/// session to that peer (see `zenoh_config`).
pub const BLOCK_WAIT_BEFORE_CLOSE_US: u64 = 60_000_000;

/// Zenoh's config for this section. Reads the password, dictionary and
/// access-control files (so a missing one is named here, at start).
pub fn zenoh_config(section: &ZenohSection) -> Result<zenoh::Config, ZenohError> {
    let mut config = zenoh::Config::default();
    let mut set = |key: &str, value: String| {
        config
            .insert_json5(key, &value)
            .map_err(|e| ZenohError::Config {
                key: key.to_string(),
                message: e.to_string(),
            })
    };
    set("mode", json(section.mode.name()))?;
    set("listen/endpoints", json_list(&section.listen))?;
    set("connect/endpoints", json_list(&section.connect))?;
    set(
        "scouting/multicast/enabled",
        section.multicast_scouting.to_string(),
    )?;
    // Timestamps on every sample, so subscribers can order and measure them.
    set("timestamping/enabled", "true".into())?;
    // A reliable put or a reply that finds its priority's queue full waits this long
    // for the link before Zenoh closes the whole session to that peer. Zenoh's 5 s
    // is shorter than a few scans take on a radio link (a 1 MB scan is 4 s at
    // 2 Mbit/s), and a closed session loses every answer in flight; the puts wait on
    // blocking threads, so a long wait holds up no one else.
    set(
        "transport/link/tx/queue/congestion_control/block/wait_before_close",
        BLOCK_WAIT_BEFORE_CLOSE_US.to_string(),
    )?;
    if section.mode == ZenohMode::Client {
        // A client that loses its router keeps trying rather than giving up.
        set("connect/timeout_ms", "-1".into())?;
    }
    let auth = &section.auth;
    if let (Some(user), Some(file)) = (&auth.user, &auth.password_file) {
        let password = read_secret(file)?;
        set("transport/auth/usrpwd/user", json(user))?;
        set("transport/auth/usrpwd/password", json(&password))?;
    }
    if let Some(file) = &auth.dictionary_file {
        // Zenoh reads it itself; check it is there so the error names our key.
        std::fs::metadata(file).map_err(|e| ZenohError::File {
            key: "zenoh.auth.dictionary_file",
            path: file.display().to_string(),
            message: e.to_string(),
        })?;
        set(
            "transport/auth/usrpwd/dictionary_file",
            json(&file.display().to_string()),
        )?;
    }
    if let Some(file) = &section.access_control {
        let text = std::fs::read_to_string(file).map_err(|e| ZenohError::File {
            key: "zenoh.access_control",
            path: file.display().to_string(),
            message: e.to_string(),
        })?;
        set("access_control", text)?;
    }
    Ok(config)
}

/// The listen endpoints with every port 0 replaced by a free port of that address
/// (Zenoh does not report the port it chose, and the log and peers need it).
pub fn with_ports_chosen(listen: &[String]) -> Result<Vec<String>, ZenohError> {
    listen
        .iter()
        .map(|e| {
            let Some(addr) = e.strip_prefix("tcp/").filter(|a| a.ends_with(":0")) else {
                return Ok(e.clone());
            };
            let bound = std::net::TcpListener::bind(addr)
                .and_then(|l| l.local_addr())
                .map_err(|err| ZenohError::Config {
                    key: "zenoh.listen".into(),
                    message: format!("{e:?}: no free port: {err}"),
                })?;
            Ok(format!("tcp/{bound}"))
        })
        .collect()
}

/// The first line of a secret file, without its line end.
fn read_secret(file: &std::path::Path) -> Result<String, ZenohError> {
    let text = std::fs::read_to_string(file).map_err(|e| ZenohError::File {
        key: "zenoh.auth.password_file",
        path: file.display().to_string(),
        message: e.to_string(),
    })?;
    let line = text.lines().next().unwrap_or("").trim_end();
    if line.is_empty() {
        return Err(ZenohError::File {
            key: "zenoh.auth.password_file",
            path: file.display().to_string(),
            message: "its first line is empty".into(),
        });
    }
    Ok(line.to_string())
}

fn json(s: &str) -> String {
    serde_json::Value::String(s.to_string()).to_string()
}

fn json_list(items: &[String]) -> String {
    serde_json::Value::from(items.to_vec()).to_string()
}
