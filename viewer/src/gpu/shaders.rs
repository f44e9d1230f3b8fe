//! The WGSL sources (files under `src/shaders/`) and how they are combined: every
//! module is `common.wgsl` followed by its own file (the modes that texture from the
//! acquisition images put `eo_camera.wgsl` before theirs).

pub const COMMON: &str = include_str!("../shaders/common.wgsl");
pub const SCAN: &str = include_str!("../shaders/scan.wgsl");
pub const MERGE: &str = include_str!("../shaders/merge.wgsl");
pub const COMPOSITE_KBUFFER: &str = include_str!("../shaders/composite_kbuffer.wgsl");
pub const COMPOSITE_NAIVE: &str = include_str!("../shaders/composite_naive.wgsl");
pub const TILE: &str = include_str!("../shaders/tile.wgsl");
pub const VDTM: &str = concat!(
    include_str!("../shaders/eo_camera.wgsl"),
    include_str!("../shaders/vdtm.wgsl")
);
pub const POINTS: &str = concat!(
    include_str!("../shaders/eo_camera.wgsl"),
    include_str!("../shaders/points.wgsl")
);
pub const POINTS_FILL: &str = include_str!("../shaders/points_fill.wgsl");
pub const TONEMAP: &str = include_str!("../shaders/tonemap.wgsl");
pub const PRESENT: &str = include_str!("../shaders/present.wgsl");

/// Every shader module as (name, full source).
pub fn modules() -> [(&'static str, String); 10] {
    [
        ("scan", source(SCAN)),
        ("merge", source(MERGE)),
        ("composite_kbuffer", source(COMPOSITE_KBUFFER)),
        ("composite_naive", source(COMPOSITE_NAIVE)),
        ("tile", source(TILE)),
        ("vdtm", source(VDTM)),
        ("tonemap", source(TONEMAP)),
        ("points", source(POINTS)),
        ("points_fill", source(POINTS_FILL)),
        ("present", source(PRESENT)),
    ]
}

/// The merge's entry point as `merge.wgsl` declares it, and with its fragment tests
/// (the stencil marks) forced before the shader, which writes storage: the
/// attribute needs a device feature (`gpu::MARK_FEATURES`), so it is added only there.
const MERGE_ENTRY: &str = "@fragment\nfn fs_merge(";
const MERGE_ENTRY_EARLY_TESTS: &str = "@fragment\n@early_depth_test(force)\nfn fs_merge(";

/// `merge.wgsl`'s full source, with the fragment tests forced early when `early_tests`.
pub fn merge_source(early_tests: bool) -> String {
    let s = source(MERGE);
    if early_tests {
        s.replace(MERGE_ENTRY, MERGE_ENTRY_EARLY_TESTS)
    } else {
        s
    }
}

/// The full source of a module: the common part, then the module's own.
pub fn source(own: &str) -> String {
    format!("{COMMON}\n{own}")
}
