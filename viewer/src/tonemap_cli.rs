//! `texel-viewer tonemap` (part of the binary, not the library): a radiance image
//! (OpenEXR, such as the simulator's truth `texel-sims view --out X.exr`) tone-mapped
//! on the GPU into a PNG, with the window's tone-mapping controls as flags.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use texel_viewer::gpu::{GpuContext, ToneMapPass, tone_map_headless};
use texel_viewer::tonemap::{ToneMapSettings, ToneOperator};

#[derive(Args)]
pub struct ToneMapArgs {
    /// The radiance image (OpenEXR, linear RGB).
    #[arg(long, value_name = "RADIANCE.exr")]
    exr: PathBuf,
    /// The PNG to write.
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    tone: ToneArgs,
}

/// The tone-mapping controls as flags (`tonemap`, and `render`/`open`/`--connect`
/// with `--hdr`).
#[derive(Args, Clone)]
pub struct ToneArgs {
    /// reinhard (Lechelek et al.'s eqs. 8-12), filmic (ACES fit) or clip.
    #[arg(long, default_value = "reinhard", value_parser = parse_operator)]
    operator: ToneOperator,
    /// Exposure in stops.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    exposure_ev: f32,
    /// Display gamma.
    #[arg(long, default_value_t = 2.2)]
    gamma: f32,
    /// The key: the display value the adaptation level maps to.
    #[arg(long, default_value_t = 0.18)]
    key: f32,
    /// A fixed adaptation level (radiance units) instead of auto-exposure from the
    /// image's log-average luminance.
    #[arg(long)]
    adaptation: Option<f32>,
}

fn parse_operator(name: &str) -> Result<ToneOperator, String> {
    ToneOperator::parse(name).ok_or_else(|| {
        let names: Vec<&str> = ToneOperator::ALL.iter().map(|o| o.name()).collect();
        format!("unknown operator {name:?}: one of {}", names.join(", "))
    })
}

impl ToneArgs {
    /// The settings, validated (a bad value named).
    pub fn settings(&self) -> anyhow::Result<ToneMapSettings> {
        let settings = ToneMapSettings {
            operator: self.operator,
            key: self.key,
            exposure_ev: self.exposure_ev,
            gamma: self.gamma,
            adaptation: self.adaptation,
        };
        settings.validate()?;
        Ok(settings)
    }
}

pub fn tonemap(args: ToneMapArgs) -> anyhow::Result<()> {
    let settings = args.tone.settings()?;
    let (width, height, radiance) = texel::radiance::exr::read_radiance_exr(&args.exr)?;
    let gpu = GpuContext::headless()?;
    let mut pass = ToneMapPass::new(&gpu);
    let (image, l_a) = tone_map_headless(&gpu, &mut pass, width, height, &radiance, &settings)?;
    image::DynamicImage::ImageRgba8(image)
        .to_rgb8()
        .save(&args.out)
        .with_context(|| format!("writing {}", args.out.display()))?;
    println!(
        "{}: {width}x{height}, {} with adaptation level {l_a:.4} ({}), exposure {:+.2} EV, gamma {}; wrote {}",
        args.exr.display(),
        settings.operator.name(),
        if args.tone.adaptation.is_some() {
            "fixed"
        } else {
            "log-average luminance"
        },
        settings.exposure_ev,
        settings.gamma,
        args.out.display()
    );
    Ok(())
}
