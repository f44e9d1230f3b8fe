//! A `texeld` process for end-to-end tests: started on a session file, its log lines
//! read on a thread and waited for by text, killed when dropped.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use crate::workspace_binary;

/// `texeld run --config SESSION`, its stderr lines on a channel.
pub struct Texeld {
    pub child: Child,
    lines: mpsc::Receiver<String>,
    /// Every line read so far.
    pub log: Vec<String>,
}

impl Texeld {
    /// Starts `texeld run --config session` (built by `cargo build -p texel-daemon`,
    /// as `cargo test --workspace` does).
    pub fn start(session: &Path) -> Self {
        Self::start_with(session, &[])
    }

    /// As [`Texeld::start`], with more arguments after the session file.
    pub fn start_with(session: &Path, extra: &[&str]) -> Self {
        let mut child = Command::new(workspace_binary("texeld"))
            .args(["run", "--config"])
            .arg(session)
            .args(extra)
            .env("NO_COLOR", "1")
            .env("RUST_LOG", "info")
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("texeld (build it with cargo build -p texel-daemon): {e}"));
        let (tx, lines) = mpsc::channel();
        if let Some(stderr) = child.stderr.take() {
            std::thread::spawn(move || {
                for line in BufReader::new(stderr).lines() {
                    let Ok(line) = line else { break };
                    if tx.send(line).is_err() {
                        break;
                    }
                }
            });
        }
        Self {
            child,
            lines,
            log: Vec::new(),
        }
    }

    /// The text after `needle` in the first log line holding it, waiting up to two
    /// minutes; panics with the log so far when none comes.
    pub fn wait_for(&mut self, needle: &str) -> String {
        let deadline = Instant::now() + Duration::from_secs(120);
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let Ok(line) = self.lines.recv_timeout(left) else {
                panic!("no log line with {needle:?}; got:\n{}", self.log.join("\n"));
            };
            self.log.push(line.clone());
            if let Some((_, rest)) = line.split_once(needle) {
                return rest.trim().to_string();
            }
        }
    }

    /// Reads the log lines that arrived so far without waiting.
    pub fn drain(&mut self) -> &[String] {
        while let Ok(line) = self.lines.try_recv() {
            self.log.push(line);
        }
        &self.log
    }
}

impl Drop for Texeld {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
