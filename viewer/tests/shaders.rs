//! Every WGSL module parses and validates with naga (no GPU needed).
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use texel_viewer::gpu::shaders;

#[test]
fn wgsl_modules_validate() {
    for (name, source) in shaders::modules() {
        let module = naga::front::wgsl::parse_str(&source)
            .unwrap_or_else(|e| panic!("{name}.wgsl: {}", e.emit_to_string(&source)));
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::default(),
        )
        .validate(&module)
        .unwrap_or_else(|e| panic!("{name}.wgsl: {}", e.emit_to_string(&source)));
        let entry_points: Vec<&str> = module
            .entry_points
            .iter()
            .map(|e| e.name.as_str())
            .collect();
        assert!(!entry_points.is_empty(), "{name}");
    }
    // The entry points the pipelines use exist.
    let scan = naga::front::wgsl::parse_str(&shaders::source(shaders::SCAN)).unwrap();
    let names: Vec<&str> = scan.entry_points.iter().map(|e| e.name.as_str()).collect();
    for want in ["vs_scan", "fs_painter", "fs_prepass", "fs_layer"] {
        assert!(names.contains(&want), "{want} in {names:?}");
    }
    let tile = naga::front::wgsl::parse_str(&shaders::source(shaders::TILE)).unwrap();
    let names: Vec<&str> = tile.entry_points.iter().map(|e| e.name.as_str()).collect();
    for want in ["vs_tile", "fs_tile"] {
        assert!(names.contains(&want), "{want} in {names:?}");
    }
}

/// The merge with its fragment tests forced before the shader (where the device can
/// merge only marked pixels) validates with that capability, and differs from the
/// plain merge by the attribute alone.
#[test]
fn the_merge_with_early_tests_validates() {
    let plain = shaders::merge_source(false);
    let early = shaders::merge_source(true);
    assert_ne!(plain, early, "the entry point was not found to mark");
    assert_eq!(early.replace("@early_depth_test(force)\n", ""), plain);
    let module = naga::front::wgsl::parse_str(&early)
        .unwrap_or_else(|e| panic!("merge.wgsl: {}", e.emit_to_string(&early)));
    naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::EARLY_DEPTH_TEST,
    )
    .validate(&module)
    .unwrap_or_else(|e| panic!("merge.wgsl: {}", e.emit_to_string(&early)));
}
