//! `texel-bench tradeoffs SECTION`: regenerates one section of `docs/tradeoffs.md`
//! ("what accuracy costs in time") from measurements made in the same run. Each
//! section owns a module (registration, rendering, calibration) that measures, writes
//! its figures under `docs/tradeoffs/` and puts the Markdown between the section's
//! markers.

pub mod calibration;
pub mod hdr;
mod hdr_render;
pub mod lod;
pub mod lod_live;
pub mod lod_view;
pub mod plot;
pub mod points;
pub mod registration;
pub mod rendering;
pub mod retirement;
pub mod surface;
pub mod vdtm_prep;

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

/// A section of `docs/tradeoffs.md`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Section {
    Registration,
}

impl Section {
    /// The marker name: `<!-- BEGIN name -->` ... `<!-- END name -->`.
    pub fn marker(self) -> &'static str {
        match self {
            Self::Registration => "registration",
        }
    }
}

/// Where a run reads and writes.
#[derive(Debug, Clone)]
pub struct Paths {
    /// The repository root (scenes, scripts, docs are found from it).
    pub repo: PathBuf,
    /// Rendered captures kept between runs.
    pub cache: PathBuf,
}

impl Paths {
    pub fn doc(&self) -> PathBuf {
        self.repo.join("docs").join("tradeoffs.md")
    }

    pub fn figures(&self) -> PathBuf {
        self.repo.join("docs").join("tradeoffs")
    }

    /// Where a quick run writes its section and figures.
    pub fn quick_dir(&self) -> PathBuf {
        self.cache.join("quick")
    }

    pub fn scenes(&self) -> PathBuf {
        self.repo.join("configs").join("scenes")
    }
}

/// The options of the sections measured on the simulator alone (`hdr`, `points`).
#[derive(Debug, Clone, clap::Args)]
pub struct SimSectionArgs {
    /// Fewer frames and held-out poses, for a quick look (docs/ is left alone).
    #[arg(long)]
    pub quick: bool,
    /// The repository root (scenes are read and the docs written under it).
    #[arg(long, default_value = ".")]
    pub repo: PathBuf,
    /// Simulator seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Measure and print, but leave docs/tradeoffs.md alone.
    #[arg(long)]
    pub no_write: bool,
}

/// Held-out views of the simulator-only sections are the EO camera scaled down by
/// this per side.
pub const SIM_VIEW_SCALE: u32 = 4;

impl SimSectionArgs {
    /// The shipped scene `name`, and a simulation of `frames` of it with the effects
    /// `effects_of` gives for it (`None`: the scene's own) and the seed asked for.
    pub fn simulate(
        &self,
        name: &str,
        frames: usize,
        effects_of: impl FnOnce(&sims::Scene) -> Option<Vec<sims::Effect>>,
    ) -> Result<(sims::Scene, sims::Simulator)> {
        let path = self
            .repo
            .join("configs/scenes")
            .join(format!("{name}.toml"));
        let scene =
            sims::Scene::load(&path).with_context(|| format!("loading {}", path.display()))?;
        let effects = effects_of(&scene);
        let sim = sims::Simulator::with_options(
            scene.clone(),
            &sims::SimOptions {
                seed: self.seed,
                frames: Some(frames),
                effects,
                ..sims::SimOptions::default()
            },
        )?;
        Ok((scene, sim))
    }
}

/// The camera of a held-out view: `eo` scaled down by [`SIM_VIEW_SCALE`] per side.
pub fn sim_view_camera(eo: &texel::PinholeCamera) -> texel::PinholeCamera {
    sims::simulator::rescale_camera(
        eo,
        (eo.width / SIM_VIEW_SCALE).max(1),
        (eo.height / SIM_VIEW_SCALE).max(1),
    )
}

/// The `p` quantile (0..=1, nearest rank) of `values`; NaN for none.
pub fn percentile(values: &[f64], p: f64) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    v.get(((v.len().saturating_sub(1)) as f64 * p.clamp(0.0, 1.0)).round() as usize)
        .copied()
        .unwrap_or(f64::NAN)
}

/// Options every section understands.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// A smaller sweep on fewer frames, for a quick look: its numbers are not the
    /// documented ones, so it writes under the cache directory, not into `docs/`.
    pub quick: bool,
    /// The Python with Open3D (the venv of `scripts/setup.sh` when not given).
    pub python: Option<PathBuf>,
}

/// Measures `section` and rewrites its part of `docs/tradeoffs.md`; a quick run
/// leaves the documentation alone and writes its section and figures under the
/// cache directory instead.
pub fn run(section: Section, paths: &Paths, options: &RunOptions) -> Result<()> {
    let body = match section {
        Section::Registration => registration::run(paths, options)?,
    };
    if options.quick {
        let out = paths.quick_dir().join(format!("{}.md", section.marker()));
        std::fs::write(&out, &body).with_context(|| format!("cannot write {}", out.display()))?;
        println!("quick run: wrote {} (docs/ unchanged)", out.display());
        return Ok(());
    }
    let doc = paths.doc();
    let text =
        std::fs::read_to_string(&doc).with_context(|| format!("cannot read {}", doc.display()))?;
    let updated = replace_section(&text, section.marker(), &body)
        .with_context(|| format!("in {}", doc.display()))?;
    std::fs::write(&doc, updated).with_context(|| format!("cannot write {}", doc.display()))?;
    println!(
        "updated the {} section of {}",
        section.marker(),
        doc.display()
    );
    Ok(())
}

/// `text` with everything between `<!-- BEGIN name -->` and `<!-- END name -->`
/// replaced by `body`; the markers stay.
pub fn replace_section(text: &str, name: &str, body: &str) -> Result<String> {
    let begin = format!("<!-- BEGIN {name} -->");
    let end = format!("<!-- END {name} -->");
    let Some(b) = text.find(&begin) else {
        bail!("no `{begin}` marker");
    };
    let after_begin = b + begin.len();
    let Some(e) = text[after_begin..].find(&end).map(|e| e + after_begin) else {
        bail!("no `{end}` marker after `{begin}`");
    };
    let body = body.trim_matches('\n');
    Ok(format!("{}\n{body}\n{}", &text[..after_begin], &text[e..]))
}

/// The venv's Python as `scripts/setup.sh` makes it: `$TEXEL_VENV`, else
/// `$XDG_CACHE_HOME/texel/venv`, else `~/.cache/texel/venv`.
pub fn venv_python() -> PathBuf {
    let venv = if let Some(v) = std::env::var_os("TEXEL_VENV") {
        PathBuf::from(v)
    } else {
        std::env::var_os("XDG_CACHE_HOME")
            .map(PathBuf::from)
            .or_else(|| std::env::var_os("HOME").map(|h| Path::new(&h).join(".cache")))
            .unwrap_or_else(|| PathBuf::from(".cache"))
            .join("texel")
            .join("venv")
    };
    venv.join("bin").join("python")
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn a_section_is_replaced_between_its_markers_only() {
        let text =
            "# T\n<!-- BEGIN a -->\nold\n<!-- END a -->\n<!-- BEGIN b -->\nkeep\n<!-- END b -->\n";
        let out = replace_section(text, "a", "\nnew 1\nnew 2\n").unwrap();
        assert_eq!(
            out,
            "# T\n<!-- BEGIN a -->\nnew 1\nnew 2\n<!-- END a -->\n<!-- BEGIN b -->\nkeep\n<!-- END b -->\n"
        );
        assert!(replace_section(text, "c", "x").is_err());
        assert!(replace_section("<!-- BEGIN a -->", "a", "x").is_err());
    }
}
