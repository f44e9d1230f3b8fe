//! The crate graph keeps the data's path: the viewer and calibration never link the
//! daemon, the simulator or the hardware crates, and the daemon's library builds
//! without the simulator. Checked with `cargo tree`, dev-dependencies included, so a
//! test-only shortcut through the daemon fails here too.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use std::process::Command;

/// Every package in `package`'s dependency tree along `edges`, with `extra` arguments
/// for `cargo tree`.
fn tree_along(edges: &str, package: &str, extra: &[&str]) -> Vec<String> {
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let out = Command::new(cargo)
        .current_dir(texel_e2e::repo_root())
        .args(["tree", "--offline", "--locked", "--prefix", "none"])
        .args(["--edges", edges, "-p", package])
        .args(extra)
        .output()
        .expect("cargo tree runs");
    assert!(
        out.status.success(),
        "cargo tree -p {package} {extra:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|line| line.split_whitespace().next())
        .map(str::to_string)
        .collect()
}

/// Every package in `package`'s dependency tree, dev-dependencies included.
fn tree(package: &str, extra: &[&str]) -> Vec<String> {
    tree_along("normal,build,dev", package, extra)
}

fn assert_free_of(package: &str, extra: &[&str], forbidden: &[&str]) {
    let packages = tree(package, extra);
    assert!(
        packages.iter().any(|p| p == package),
        "cargo tree -p {package} listed no {package}: {packages:?}"
    );
    for name in forbidden {
        assert!(
            !packages.iter().any(|p| p == name),
            "{package} {extra:?} depends on {name}"
        );
    }
}

const DAEMON_AND_HARDWARE: [&str; 4] = ["texel-daemon", "sims", "v4l", "tokio-serial"];

#[test]
fn the_viewer_links_neither_the_daemon_nor_the_simulator_nor_hardware() {
    assert_free_of("texel-viewer", &[], &DAEMON_AND_HARDWARE);
    assert_free_of("texel-viewer", &[], &["texel-bench"]);
}

#[test]
fn calibration_links_neither_the_daemon_nor_the_simulator_nor_hardware() {
    assert_free_of("calib", &[], &DAEMON_AND_HARDWARE);
    assert_free_of("calib", &[], &["texel-bench"]);
}

#[test]
fn the_daemon_builds_without_the_simulator() {
    assert_free_of("texel-daemon", &["--no-default-features"], &["sims"]);
}

#[test]
fn the_pure_stages_and_the_shared_vocabulary_stay_free_of_services() {
    // Dev-dependencies aside (registration's tests use the simulator for truth).
    for package in [
        "texel",
        "texel-register",
        "texel-surface",
        "texel-vdtm",
        "texel-lod",
        "texel-client",
    ] {
        let packages = tree_along("normal,build", package, &[]);
        // The client's async transport is an opt-in feature; the others take none.
        let services: &[&str] = if package == "texel-client" {
            &["texel-bench", "wgpu"]
        } else {
            &["texel-bench", "wgpu", "tokio"]
        };
        for name in DAEMON_AND_HARDWARE.iter().chain(services) {
            assert!(
                !packages.iter().any(|p| p == name),
                "{package} depends on {name}"
            );
        }
    }
}

#[test]
fn no_product_crate_depends_on_the_tooling_crate() {
    for package in [
        "texel",
        "texel-register",
        "texel-surface",
        "texel-vdtm",
        "texel-lod",
        "texel-client",
        "calib",
        "sims",
        "texel-daemon",
        "texel-viewer",
    ] {
        assert_free_of(package, &[], &["texel-bench"]);
    }
}
