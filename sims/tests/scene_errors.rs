//! Bad scenes are refused with the file, line and key; nothing panics.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

mod common;

use common::{configs, fixed_camera_scene};
use sims::{Scene, SceneError};

fn parse(text: &str) -> Result<Scene, SceneError> {
    Scene::from_toml_str(text, "bad.toml", &configs().join("scenes"))
}

fn line_of(text: &str, needle: &str) -> usize {
    text.lines().position(|l| l.contains(needle)).unwrap() + 1
}

#[test]
fn unknown_keys_name_file_line_and_key() {
    let text = fixed_camera_scene(
        "[[objects.box]]\nmaterial = \"grey\"\nsize = [1.0, 1.0, 1.0]\ncolour = 3\n",
    );
    let e = parse(&text).unwrap_err();
    assert_eq!(e.origin, "bad.toml");
    assert_eq!(e.line, Some(line_of(&text, "colour")));
    assert_eq!(e.key, "colour");
    let shown = e.to_string();
    assert!(
        shown.starts_with(&format!("bad.toml:{}: colour:", line_of(&text, "colour"))),
        "{shown}"
    );
    let text = fixed_camera_scene("[[objects.cone]]\nmaterial = \"grey\"\n");
    let e = parse(&text).unwrap_err();
    assert!(
        e.message.contains("cone") && e.message.contains("sphere"),
        "{e}"
    );
}

#[test]
fn an_unknown_effect_lists_the_valid_ones() {
    let text = fixed_camera_scene("").replace(
        "[trajectory]",
        "effects = [\"range_noise\", \"fog\"]\n[trajectory]",
    );
    let e = parse(&text).unwrap_err();
    assert_eq!(e.key, "effects[1]");
    assert_eq!(e.line, Some(line_of(&text, "fog")));
    for name in sims::effects::EFFECT_NAMES {
        assert!(e.message.contains(name), "{e}");
    }
    let text = fixed_camera_scene("").replace(
        "[trajectory]",
        "effects = [{ name = \"dropouts\", max_incidence_deg = 200.0 }]\n[trajectory]",
    );
    let e = parse(&text).unwrap_err();
    assert!(e.message.contains("max_incidence_deg"), "{e}");
    let text = fixed_camera_scene("").replace(
        "[trajectory]",
        "effects = [\"vignetting\", \"vignetting\"]\n[trajectory]",
    );
    assert!(parse(&text).unwrap_err().message.contains("twice"));
}

#[test]
fn unknown_materials_missing_files_and_bad_values_are_named() {
    let text = fixed_camera_scene("[[objects.sphere]]\nmaterial = \"gold\"\nradius = 1.0\n");
    let e = parse(&text).unwrap_err();
    assert_eq!(e.key, "objects.sphere[0].material");
    assert_eq!(e.line, Some(line_of(&text, "gold")));
    assert!(e.message.contains("checks, grey"), "{e}");

    let text = fixed_camera_scene(
        "[materials.poster]\nimage = { file = \"nope.png\", size_m = [1.0, 1.0] }\n",
    );
    let e = parse(&text).unwrap_err();
    assert_eq!(e.key, "materials.poster.image.file");
    assert_eq!(e.line, Some(line_of(&text, "nope.png")));
    assert!(e.message.contains("nope.png"), "{e}");

    let text =
        fixed_camera_scene("[[objects.mesh]]\nmaterial = \"grey\"\nfile = \"missing.obj\"\n");
    let e = parse(&text).unwrap_err();
    assert_eq!(e.key, "objects.mesh[0].file");
    assert!(e.message.contains("missing.obj"), "{e}");

    let text = fixed_camera_scene("[[objects.sphere]]\nmaterial = \"grey\"\nradius = -1.0\n");
    let e = parse(&text).unwrap_err();
    assert_eq!(e.key, "objects.sphere[0].radius");

    let text = fixed_camera_scene("").replace("rate_hz = 10.0", "rate_hz = 0.0");
    assert_eq!(parse(&text).unwrap_err().key, "trajectory.rate_hz");
    let text = fixed_camera_scene("").replace(
        "sensor = \"../sensors/texel-default.toml\"",
        "sensor = \"nowhere.toml\"",
    );
    let e = parse(&text).unwrap_err();
    assert_eq!((e.key.as_str(), e.line), ("sensor", Some(2)));
    assert!(e.message.contains("nowhere.toml"));
}

#[test]
fn bad_brick_parameters_are_named() {
    let good = "brick_m = [0.24, 0.08], mortar_m = 0.01, palette = [[0.6, 0.25, 0.15]]";
    let text = fixed_camera_scene(&format!("[materials.wall]\nbricks = {{ {good} }}\n"));
    parse(&text).unwrap();
    for (bad, key) in [
        (good.replace("[0.24, 0.08]", "[0.24, 0.0]"), "brick_m"),
        (good.replace("[0.24, 0.08]", "[0.24]"), "bricks"),
        (
            good.replace("mortar_m = 0.01", "mortar_m = 0.08"),
            "mortar_m",
        ),
        (
            good.replace("mortar_m = 0.01", "mortar_m = -0.01"),
            "mortar_m",
        ),
        (good.replace("[[0.6, 0.25, 0.15]]", "[]"), "palette"),
        (good.replace("0.25, 0.15]]", "1.5, 0.15]]"), "palette"),
        (format!("{good}, variation = 2.0"), "variation"),
        (
            format!("{good}, mortar_color = [0.5, -1.0, 0.5]"),
            "mortar_color",
        ),
        (format!("{good}, mortar = [0.5, 0.5, 0.5]"), "mortar"),
    ] {
        let text = fixed_camera_scene(&format!("[materials.wall]\nbricks = {{ {bad} }}\n"));
        let e = parse(&text).unwrap_err();
        assert!(e.key.contains(key) || e.message.contains(key), "{bad}: {e}");
        // The material's table, or the line of the key serde refused.
        let lines = [line_of(&text, "[materials.wall]"), line_of(&text, "bricks")];
        assert!(e.line.is_some_and(|l| lines.contains(&l)), "{bad}: {e}");
    }
    let text = fixed_camera_scene(&format!(
        "[materials.wall]\ncolor = [0.5, 0.5, 0.5]\nbricks = {{ {good} }}\n"
    ));
    assert!(parse(&text).unwrap_err().message.contains("bricks"));
}

#[test]
fn sizes_beyond_the_limits_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let sensor = std::fs::read_to_string(configs().join("sensors/texel-default.toml"))
        .unwrap()
        .replacen("width = 128", "width = 2048", 1);
    std::fs::write(dir.path().join("big.toml"), sensor).unwrap();
    let text = fixed_camera_scene("").replace("../sensors/texel-default.toml", "big.toml");
    let e = Scene::from_toml_str(&text, "big-scene.toml", dir.path()).unwrap_err();
    assert!(
        e.message.contains("2048") && e.message.contains("1024"),
        "{e}"
    );
    let text = fixed_camera_scene("").replace("rate_hz = 10.0", "rate_hz = 10.0\nframes = 5000000");
    assert_eq!(parse(&text).unwrap_err().key, "trajectory.frames");
    let sim = sims::Simulator::with_options(
        parse(&fixed_camera_scene("")).unwrap(),
        &sims::SimOptions {
            eo_size: Some([100_000, 10]),
            ..Default::default()
        },
    );
    assert!(matches!(sim, Err(sims::SimError::BadOption(_))));
}

#[test]
fn unreadable_meshes_are_named_and_good_ones_render() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("broken.obj"), "v 0 0 0\nv 1 0 0\nf 1 2 9\n").unwrap();
    std::fs::write(
        dir.path().join("quad.obj"),
        "v -2 0 -2\nv 2 0 -2\nv 2 0 2\nv -2 0 2\nf 1 2 3 4\n",
    )
    .unwrap();
    std::fs::copy(
        configs().join("sensors/texel-default.toml"),
        dir.path().join("s.toml"),
    )
    .unwrap();
    let base = fixed_camera_scene("").replace("../sensors/texel-default.toml", "s.toml");
    let text = format!("{base}[[objects.mesh]]\nmaterial = \"grey\"\nfile = \"broken.obj\"\n");
    let e = Scene::from_toml_str(&text, "m.toml", dir.path()).unwrap_err();
    assert!(
        e.message.contains("broken.obj") && e.message.contains("line 3"),
        "{e}"
    );
    // The quad, moved to y = 3: a wall 3 m ahead of the first pose's camera.
    let text = format!(
        "{base}[[objects.mesh]]\nmaterial = \"grey\"\nfile = \"quad.obj\"\nposition = [0.0, 3.0, 1.0]\n"
    );
    let scene = Scene::from_toml_str(&text, "m.toml", dir.path()).unwrap();
    let hit = scene
        .cast_ray(nalgebra::Point3::new(0.0, 0.0, 1.0), nalgebra::Vector3::y())
        .unwrap();
    assert!((hit.distance_m - 3.0).abs() < 1e-12);
}

#[test]
fn garbage_never_panics() {
    let good = fixed_camera_scene("[[objects.box]]\nmaterial = \"grey\"\nsize = [1.0, 1.0, 1.0]\n");
    for cut in (0..good.len()).step_by(7) {
        let _ = parse(&good[..cut]);
    }
    for junk in [
        "",
        "[[[",
        "sensor = 3",
        "objects = 5",
        "trajectory = []",
        "\u{0}\u{1}",
    ] {
        assert!(parse(junk).is_err());
    }
}
