//! Helpers shared by the end-to-end tests in `tests/tests/`: where the repository,
//! its scripts and the Python venv of peer tools are.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The repository root.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."))
}

/// The venv that `scripts/setup.sh` creates: `$TEXEL_VENV`, else
/// `$XDG_CACHE_HOME/texel/venv`, else `~/.cache/texel/venv`.
pub fn venv_dir() -> PathBuf {
    if let Some(v) = std::env::var_os("TEXEL_VENV") {
        return PathBuf::from(v);
    }
    let cache = std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))
        .unwrap_or_else(|| PathBuf::from(".cache"));
    cache.join("texel").join("venv")
}

/// The venv's Python. Panics with the set-up command when it is missing: the
/// interop tests are part of the suite, not optional.
pub fn python() -> PathBuf {
    let python = venv_dir().join("bin").join("python");
    assert!(
        python.exists(),
        "the Python venv with the peer tools is missing at {}; run scripts/setup.sh \
         (the README's test command does this)",
        python.display()
    );
    python
}

/// Runs `scripts/python/<script>` with the venv's Python; panics with its stderr if
/// it fails.
pub fn run_python(script: &str, args: &[&std::ffi::OsStr]) -> Output {
    let path = repo_root().join("scripts").join("python").join(script);
    let output = Command::new(python())
        .arg(&path)
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("cannot run {}: {e}", path.display()));
    assert!(
        output.status.success(),
        "{script} failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    output
}

/// The path of a binary of this workspace, built by cargo for the tests.
pub fn workspace_binary(name: &str) -> PathBuf {
    // Integration tests run from target/<profile>/deps; binaries sit one level up.
    let exe = std::env::current_exe().unwrap_or_default();
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .map(Path::to_path_buf)
        .unwrap_or_default();
    dir.join(name)
}
