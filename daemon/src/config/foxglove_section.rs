//! The `[foxglove]` section: offering the live session to the Foxglove app over the
//! Foxglove WebSocket protocol (`docs/daemon.md`, "Live in Foxglove"): whether, where,
//! and how much a slow Foxglove client may have queued.

use std::net::SocketAddr;

use serde::Deserialize;

/// The most messages a Foxglove client may have queued: each can be a whole image or
/// a scan's model (about a megabyte), so more is memory, not smoothness.
pub const MAX_FOXGLOVE_CLIENT_QUEUE: usize = 4096;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FoxgloveSection {
    /// Start the Foxglove WebSocket server. Off by default: a plain session opens no
    /// port beyond the viewer port.
    pub enabled: bool,
    /// Where the server listens; port 0 picks a free port (the log says which).
    pub bind: SocketAddr,
    /// The Foxglove WebSocket protocol has no authentication: a bind beyond loopback
    /// is refused unless this is set, and then anyone who reaches the port sees the
    /// camera.
    pub allow_remote: bool,
    /// Messages queued per Foxglove client (the foxglove crate's message backlog):
    /// when it is full the oldest queued message is dropped for the new one.
    pub client_queue: usize,
}

impl Default for FoxgloveSection {
    fn default() -> Self {
        Self {
            enabled: false,
            bind: SocketAddr::from(([127, 0, 0, 1], 8765)),
            allow_remote: false,
            client_queue: 256,
        }
    }
}

impl FoxgloveSection {
    /// Checks what the types cannot; `Err((key, message))`.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        if !self.enabled {
            return Ok(());
        }
        if !cfg!(feature = "foxglove-live") {
            return Err((
                "foxglove.enabled",
                "this texeld was built without the Foxglove server (the cargo feature \
                 `foxglove-live`)"
                    .into(),
            ));
        }
        if !(1..=MAX_FOXGLOVE_CLIENT_QUEUE).contains(&self.client_queue) {
            return Err((
                "foxglove.client_queue",
                format!(
                    "must be in 1..={MAX_FOXGLOVE_CLIENT_QUEUE}, got {}",
                    self.client_queue
                ),
            ));
        }
        if !self.bind.ip().is_loopback() && !self.allow_remote {
            return Err((
                "foxglove.bind",
                format!(
                    "{} is not loopback, and the Foxglove WebSocket protocol has no \
                     authentication: anyone who reaches the port would see the camera; \
                     set foxglove.allow_remote = true to bind there anyway",
                    self.bind
                ),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_remote_bind_needs_allow_remote() {
        let mut s = FoxgloveSection {
            enabled: true,
            bind: SocketAddr::from(([0, 0, 0, 0], 8765)),
            ..FoxgloveSection::default()
        };
        if cfg!(feature = "foxglove-live") {
            assert_eq!(s.validate().map_err(|e| e.0), Err("foxglove.bind"));
            s.allow_remote = true;
            assert!(s.validate().is_ok());
        } else {
            assert_eq!(s.validate().map_err(|e| e.0), Err("foxglove.enabled"));
        }
        s.enabled = false;
        assert!(s.validate().is_ok());
    }
}
