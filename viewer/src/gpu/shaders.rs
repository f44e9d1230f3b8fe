//! The WGSL sources (files under `src/shaders/`) and how they are combined: every
//! module is `common.wgsl` followed by its own file.

pub const COMMON: &str = include_str!("../shaders/common.wgsl");
pub const SCAN: &str = include_str!("../shaders/scan.wgsl");
pub const MERGE: &str = include_str!("../shaders/merge.wgsl");
pub const COMPOSITE_KBUFFER: &str = include_str!("../shaders/composite_kbuffer.wgsl");
pub const COMPOSITE_NAIVE: &str = include_str!("../shaders/composite_naive.wgsl");
pub const TILE: &str = include_str!("../shaders/tile.wgsl");
pub const VDTM: &str = include_str!("../shaders/vdtm.wgsl");
pub const TONEMAP: &str = include_str!("../shaders/tonemap.wgsl");

/// Every shader module as (name, full source).
pub fn modules() -> [(&'static str, String); 7] {
    [
        ("scan", source(SCAN)),
        ("merge", source(MERGE)),
        ("composite_kbuffer", source(COMPOSITE_KBUFFER)),
        ("composite_naive", source(COMPOSITE_NAIVE)),
        ("tile", source(TILE)),
        ("vdtm", source(VDTM)),
        ("tonemap", source(TONEMAP)),
    ]
}

/// The full source of a module: the common part, then the module's own.
pub fn source(own: &str) -> String {
    format!("{COMMON}\n{own}")
}
