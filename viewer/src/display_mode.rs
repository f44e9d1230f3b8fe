//! What the viewer draws: the scans composited per pixel (Killpack & Budge 2016, one
//! of the compositing modes) or the merged surface textured view-dependently
//! (Debevec 1998, `vdtm`).

use crate::composite::Mode;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DisplayMode {
    Scans(Mode),
    Vdtm,
}

impl DisplayMode {
    /// The compositing mode the scans use (also while VDTM's first build runs).
    pub fn scans_mode(self) -> Mode {
        match self {
            DisplayMode::Scans(m) => m,
            DisplayMode::Vdtm => Mode::default(),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            DisplayMode::Scans(m) => m.name(),
            DisplayMode::Vdtm => "vdtm",
        }
    }
}

impl std::str::FromStr for DisplayMode {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        if s == "vdtm" {
            return Ok(DisplayMode::Vdtm);
        }
        s.parse::<Mode>()
            .map(DisplayMode::Scans)
            .map_err(|e| format!("{e}, vdtm"))
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
        let err = "vdtmx".parse::<DisplayMode>().unwrap_err();
        assert!(err.contains("vdtm") && err.contains("blended"), "{err}");
    }
}
