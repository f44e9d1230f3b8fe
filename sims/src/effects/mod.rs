//! The effects a scene may call for. Each effect is its own stage with its own module
//! (physical model, parameters with units, defaults); only the effects a scene lists
//! run, and an effect that is not listed costs nothing: the pipeline checks an
//! `Option` per stage and skips it.
//!
//! Lidar pipeline, per pixel: beam geometry (`mixed_pixels`, else one ray) →
//! `dropouts` → `range_noise` → `range_quantisation`.
//! EO pipeline, per pixel: camera model (`lens_distortion`) → radiance (`moving_lights`
//! sets the lights of the frame's time; `specular` adds the glossy lobe; `motion_blur`
//! averages sub-exposures) → `vignetting` →
//! exposure (`exposure`, else exposure 0 EV) → `sensor_noise` → response curve
//! (`exposure`'s, else sRGB) → 8 bits.

pub mod dropouts;
pub mod exposure;
pub mod global_illumination;
pub mod lens_distortion;
pub mod mixed_pixels;
pub mod motion_blur;
pub mod moving_lights;
pub mod range_noise;
pub mod range_quantisation;
pub mod sensor_noise;
pub mod specular;
pub mod vignetting;

use serde::Serialize;
use serde::de::DeserializeOwned;

pub use dropouts::Dropouts;
pub use exposure::{Exposure, Response};
pub use global_illumination::GlobalIllumination;
pub use lens_distortion::LensDistortion;
pub use mixed_pixels::MixedPixels;
pub use motion_blur::MotionBlur;
pub use moving_lights::MovingLights;
pub use range_noise::RangeNoiseEffect;
pub use range_quantisation::RangeQuantisation;
pub use sensor_noise::SensorNoise;
pub use specular::Specular;
pub use vignetting::Vignetting;

/// One parameter's documentation.
#[derive(Debug, Clone, Copy)]
pub struct ParamDoc {
    pub name: &'static str,
    pub unit: &'static str,
    pub what: &'static str,
}

/// Which sensor an effect acts on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Target {
    Lidar,
    Eo,
    /// Both cameras (the shared optics).
    Optics,
}

/// What every effect's parameter block provides.
pub trait EffectParams: Default + Serialize + DeserializeOwned + Clone + PartialEq {
    const NAME: &'static str;
    const TARGET: Target;
    /// One paragraph: the physical model.
    const MODEL: &'static str;
    const PARAMS: &'static [ParamDoc];
    /// Only the Mitsuba backend simulates this effect (asking for it selects it).
    const NEEDS_MITSUBA: bool = false;
    /// Checks values a physical device can have; the message names the parameter.
    fn validate(&self) -> Result<(), String>;
}

/// One effect with its parameters.
#[derive(Debug, Clone, PartialEq)]
pub enum Effect {
    RangeNoise(RangeNoiseEffect),
    Dropouts(Dropouts),
    MixedPixels(MixedPixels),
    RangeQuantisation(RangeQuantisation),
    LensDistortion(LensDistortion),
    Vignetting(Vignetting),
    SensorNoise(SensorNoise),
    Exposure(Exposure),
    MotionBlur(MotionBlur),
    Specular(Specular),
    GlobalIllumination(GlobalIllumination),
    MovingLights(MovingLights),
}

/// Every effect's name, in pipeline order.
pub const EFFECT_NAMES: [&str; 12] = [
    MixedPixels::NAME,
    Dropouts::NAME,
    RangeNoiseEffect::NAME,
    RangeQuantisation::NAME,
    LensDistortion::NAME,
    MovingLights::NAME,
    Specular::NAME,
    GlobalIllumination::NAME,
    MotionBlur::NAME,
    Vignetting::NAME,
    Exposure::NAME,
    SensorNoise::NAME,
];

/// Documentation of one effect, for `texel-sims effects` and docs.
#[derive(Debug, Clone)]
pub struct EffectDoc {
    pub name: &'static str,
    pub target: Target,
    pub model: &'static str,
    /// `(doc, default value as TOML text)` per parameter.
    pub params: Vec<(ParamDoc, String)>,
    /// Only the Mitsuba backend simulates it.
    pub needs_mitsuba: bool,
}

fn doc_of<P: EffectParams>() -> EffectDoc {
    let defaults = toml::Value::try_from(P::default())
        .ok()
        .and_then(|v| v.as_table().cloned())
        .unwrap_or_default();
    EffectDoc {
        name: P::NAME,
        target: P::TARGET,
        model: P::MODEL,
        params: P::PARAMS
            .iter()
            .map(|d| {
                let default = defaults
                    .get(d.name)
                    .map_or_else(|| "?".to_string(), |v| v.to_string());
                (*d, default)
            })
            .collect(),
        needs_mitsuba: P::NEEDS_MITSUBA,
    }
}

/// Documentation of every effect, in pipeline order.
pub fn effect_docs() -> Vec<EffectDoc> {
    vec![
        doc_of::<MixedPixels>(),
        doc_of::<Dropouts>(),
        doc_of::<RangeNoiseEffect>(),
        doc_of::<RangeQuantisation>(),
        doc_of::<LensDistortion>(),
        doc_of::<MovingLights>(),
        doc_of::<Specular>(),
        doc_of::<GlobalIllumination>(),
        doc_of::<MotionBlur>(),
        doc_of::<Vignetting>(),
        doc_of::<Exposure>(),
        doc_of::<SensorNoise>(),
    ]
}

fn parse_params<P: EffectParams>(table: toml::Table) -> Result<P, String> {
    let params: P = toml::Value::Table(table)
        .try_into()
        .map_err(|e: toml::de::Error| format!("{}: {}", P::NAME, e.message().trim()))?;
    params.validate().map_err(|m| format!("{}: {m}", P::NAME))?;
    Ok(params)
}

impl Effect {
    pub fn name(&self) -> &'static str {
        match self {
            Self::RangeNoise(_) => RangeNoiseEffect::NAME,
            Self::Dropouts(_) => Dropouts::NAME,
            Self::MixedPixels(_) => MixedPixels::NAME,
            Self::RangeQuantisation(_) => RangeQuantisation::NAME,
            Self::LensDistortion(_) => LensDistortion::NAME,
            Self::Vignetting(_) => Vignetting::NAME,
            Self::SensorNoise(_) => SensorNoise::NAME,
            Self::Exposure(_) => Exposure::NAME,
            Self::MotionBlur(_) => MotionBlur::NAME,
            Self::Specular(_) => Specular::NAME,
            Self::GlobalIllumination(_) => GlobalIllumination::NAME,
            Self::MovingLights(_) => MovingLights::NAME,
        }
    }

    /// The effect `name` with `params` (a TOML table, possibly empty).
    pub fn from_name_and_params(name: &str, params: toml::Table) -> Result<Self, String> {
        Ok(match name {
            RangeNoiseEffect::NAME => Self::RangeNoise(parse_params(params)?),
            Dropouts::NAME => Self::Dropouts(parse_params(params)?),
            MixedPixels::NAME => Self::MixedPixels(parse_params(params)?),
            RangeQuantisation::NAME => Self::RangeQuantisation(parse_params(params)?),
            LensDistortion::NAME => Self::LensDistortion(parse_params(params)?),
            Vignetting::NAME => Self::Vignetting(parse_params(params)?),
            SensorNoise::NAME => Self::SensorNoise(parse_params(params)?),
            Exposure::NAME => Self::Exposure(parse_params(params)?),
            MotionBlur::NAME => Self::MotionBlur(parse_params(params)?),
            Specular::NAME => Self::Specular(parse_params(params)?),
            GlobalIllumination::NAME => Self::GlobalIllumination(parse_params(params)?),
            MovingLights::NAME => Self::MovingLights(parse_params(params)?),
            other => {
                return Err(format!(
                    "unknown effect {other:?}; valid effects are: {}",
                    EFFECT_NAMES.join(", ")
                ));
            }
        })
    }

    /// An effect with its default parameters.
    pub fn with_defaults(name: &str) -> Result<Self, String> {
        Self::from_name_and_params(name, toml::Table::new())
    }

    /// Parses one entry of a scene's `effects` array: a name (`"range_noise"`) or a
    /// table with `name` and parameters (`{ name = "dropouts", max_incidence_deg = 80 }`).
    pub fn from_toml(value: &toml::Value) -> Result<Self, String> {
        match value {
            toml::Value::String(name) => Self::with_defaults(name),
            toml::Value::Table(table) => {
                let mut params = table.clone();
                let name = match params.remove("name") {
                    Some(toml::Value::String(n)) => n,
                    Some(_) => return Err("effect `name` must be a string".into()),
                    None => {
                        return Err(format!(
                            "an effect table needs a `name` (one of: {})",
                            EFFECT_NAMES.join(", ")
                        ));
                    }
                };
                Self::from_name_and_params(&name, params)
            }
            _ => Err("an effect is a name or a table { name = ..., parameters }".into()),
        }
    }
}

/// The effects of one simulation, one slot per stage (`None` = not simulated).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct EffectSet {
    pub range_noise: Option<RangeNoiseEffect>,
    pub dropouts: Option<Dropouts>,
    pub mixed_pixels: Option<MixedPixels>,
    pub range_quantisation: Option<RangeQuantisation>,
    pub lens_distortion: Option<LensDistortion>,
    pub vignetting: Option<Vignetting>,
    pub sensor_noise: Option<SensorNoise>,
    pub exposure: Option<Exposure>,
    pub motion_blur: Option<MotionBlur>,
    pub specular: Option<Specular>,
    pub global_illumination: Option<GlobalIllumination>,
    pub moving_lights: Option<MovingLights>,
}

impl EffectSet {
    /// Collects a list; an effect listed twice is an error naming it.
    pub fn from_list(effects: &[Effect]) -> Result<Self, String> {
        let mut set = Self::default();
        for e in effects {
            let dup = match e.clone() {
                Effect::RangeNoise(p) => set.range_noise.replace(p).is_some(),
                Effect::Dropouts(p) => set.dropouts.replace(p).is_some(),
                Effect::MixedPixels(p) => set.mixed_pixels.replace(p).is_some(),
                Effect::RangeQuantisation(p) => set.range_quantisation.replace(p).is_some(),
                Effect::LensDistortion(p) => set.lens_distortion.replace(p).is_some(),
                Effect::Vignetting(p) => set.vignetting.replace(p).is_some(),
                Effect::SensorNoise(p) => set.sensor_noise.replace(p).is_some(),
                Effect::Exposure(p) => set.exposure.replace(p).is_some(),
                Effect::MotionBlur(p) => set.motion_blur.replace(p).is_some(),
                Effect::Specular(p) => set.specular.replace(p).is_some(),
                Effect::GlobalIllumination(p) => set.global_illumination.replace(p).is_some(),
                Effect::MovingLights(p) => set.moving_lights.replace(p).is_some(),
            };
            if dup {
                return Err(format!("effect {:?} is listed twice", e.name()));
            }
        }
        Ok(set)
    }

    /// True when no lidar effect runs.
    pub fn lidar_is_clean(&self) -> bool {
        self.range_noise.is_none()
            && self.dropouts.is_none()
            && self.mixed_pixels.is_none()
            && self.range_quantisation.is_none()
    }

    /// Names of the effects in the set, in pipeline order.
    pub fn names(&self) -> Vec<&'static str> {
        let present = [
            self.mixed_pixels.is_some(),
            self.dropouts.is_some(),
            self.range_noise.is_some(),
            self.range_quantisation.is_some(),
            self.lens_distortion.is_some(),
            self.moving_lights.is_some(),
            self.specular.is_some(),
            self.global_illumination.is_some(),
            self.motion_blur.is_some(),
            self.vignetting.is_some(),
            self.exposure.is_some(),
            self.sensor_noise.is_some(),
        ];
        EFFECT_NAMES
            .iter()
            .zip(present)
            .filter_map(|(n, p)| p.then_some(*n))
            .collect()
    }
}

/// `Ok` when `value` is finite and within `range`; otherwise a message naming `name`.
pub(crate) fn check_range(
    name: &str,
    value: f64,
    range: std::ops::RangeInclusive<f64>,
) -> Result<(), String> {
    if value.is_finite() && range.contains(&value) {
        Ok(())
    } else {
        Err(format!(
            "{name} = {value} is outside [{}, {}]",
            range.start(),
            range.end()
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_parameter_is_documented_with_its_default() {
        for doc in effect_docs() {
            for (p, default) in &doc.params {
                assert_ne!(default, "?", "{}.{} has no default", doc.name, p.name);
                assert!(!p.unit.is_empty() && !p.what.is_empty());
            }
            // And every serialised field has a doc entry.
            let e = Effect::with_defaults(doc.name).unwrap();
            assert_eq!(e.name(), doc.name);
        }
        assert_eq!(effect_docs().len(), EFFECT_NAMES.len());
    }

    #[test]
    fn unknown_effects_and_parameters_are_named() {
        let e = Effect::with_defaults("fog").unwrap_err();
        assert!(
            e.contains("fog") && e.contains("range_noise") && e.contains("vignetting"),
            "{e}"
        );
        let v: toml::Value =
            toml::from_str::<toml::Table>("e = { name = \"dropouts\", max_incidence = 3 }")
                .unwrap()
                .remove("e")
                .unwrap();
        let e = Effect::from_toml(&v).unwrap_err();
        assert!(e.contains("dropouts") && e.contains("max_incidence"), "{e}");
        let dup = EffectSet::from_list(&[
            Effect::with_defaults("range_noise").unwrap(),
            Effect::with_defaults("range_noise").unwrap(),
        ]);
        assert!(dup.unwrap_err().contains("twice"));
    }
}
