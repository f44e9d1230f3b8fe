//! What the viewer draws: the scans composited per pixel (Killpack & Budge 2016, one
//! of the compositing modes) or the merged surface textured view-dependently
//! (Debevec 1998, `vdtm`), or the scans as a point proxy with per-view depth maps
//! (Lechelek et al. 2019, `points`).

use crate::composite::Mode;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DisplayMode {
    Scans(Mode),
    Vdtm,
    Points,
}

impl DisplayMode {
    /// The compositing mode the scans use (also while VDTM's first build runs).
    pub fn scans_mode(self) -> Mode {
        match self {
            DisplayMode::Scans(m) => m,
            DisplayMode::Vdtm | DisplayMode::Points => Mode::default(),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            DisplayMode::Scans(m) => m.name(),
            DisplayMode::Vdtm => "vdtm",
            DisplayMode::Points => "points",
        }
    }
}

impl std::str::FromStr for DisplayMode {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "vdtm" => return Ok(DisplayMode::Vdtm),
            "points" => return Ok(DisplayMode::Points),
            _ => {}
        }
        s.parse::<Mode>()
            .map(DisplayMode::Scans)
            .map_err(|e| format!("{e}, vdtm, points"))
    }
}

impl std::fmt::Display for DisplayMode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_mode_parses_back_from_its_name() {
        for m in Mode::ALL {
            let d = DisplayMode::Scans(m);
            assert_eq!(d.name().parse::<DisplayMode>(), Ok(d));
        }
        assert_eq!("vdtm".parse::<DisplayMode>(), Ok(DisplayMode::Vdtm));
        assert_eq!("points".parse::<DisplayMode>(), Ok(DisplayMode::Points));
        let err = "vdtmx".parse::<DisplayMode>().unwrap_err();
        assert!(
            err.contains("vdtm") && err.contains("points") && err.contains("blended"),
            "{err}"
        );
    }
}
