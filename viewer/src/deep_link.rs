//! The field display's deep links: the page's query string (`?mode=blended&pose=...`)
//! read into a fixed view. The same mode names and pose text as `texel-viewer render`
//! (`--mode`, `--pose "x y z qx qy qz qw"`), so a view found on the command line opens
//! in the browser and back. A token never travels here: links get shared and logged.

use texel::Pose;

use crate::display_mode::DisplayMode;

/// What a link fixes; `None`: the viewer's own choice.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DeepLink {
    pub mode: Option<DisplayMode>,
    /// world_from_eo of the virtual camera (EO frame: x right, y down, z forward).
    pub pose: Option<Pose>,
    pub fov_deg: Option<f64>,
    /// Blend at most this many fragments.
    pub k: Option<u32>,
    /// Tell the page's watchers it is ready once this many scans are drawn.
    pub ready_scans: Option<usize>,
}

/// Why a link was not understood.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DeepLinkError {
    #[error("?{key}={value:?}: {reason}")]
    Value {
        key: &'static str,
        value: String,
        reason: String,
    },
    #[error(
        "?token= is not accepted: a token in a link ends up in histories and logs; \
         the page asks for it instead"
    )]
    TokenInLink,
}

impl DeepLink {
    /// Reads a query string (with or without its leading `?`). Unknown keys are
    /// ignored, so links made by a newer page still open; a known key with a bad
    /// value is an error naming it.
    pub fn parse(query: &str) -> Result<Self, DeepLinkError> {
        let mut link = DeepLink::default();
        for pair in query.trim_start_matches('?').split('&') {
            if pair.is_empty() {
                continue;
            }
            let (key, raw) = pair.split_once('=').unwrap_or((pair, ""));
            let value = percent_decode(raw);
            let bad = |key: &'static str, reason: String| DeepLinkError::Value {
                key,
                value: value.clone(),
                reason,
            };
            match key {
                "mode" => link.mode = Some(value.parse().map_err(|e| bad("mode", e))?),
                "pose" => {
                    // Commas or spaces between the seven numbers.
                    let text = value.replace(',', " ");
                    let pose =
                        texel::pose::parse_pose(&text).map_err(|e| bad("pose", e.to_string()))?;
                    link.pose = Some(pose);
                }
                "fov" => {
                    let fov: f64 = value
                        .parse()
                        .map_err(|e: std::num::ParseFloatError| bad("fov", e.to_string()))?;
                    if !(fov.is_finite() && fov > 1.0 && fov < 179.0) {
                        return Err(bad("fov", "a field of view in degrees, 1..179".into()));
                    }
                    link.fov_deg = Some(fov);
                }
                "k" => {
                    let k: u32 = value
                        .parse()
                        .map_err(|e: std::num::ParseIntError| bad("k", e.to_string()))?;
                    if !(1..=crate::composite::MAX_K).contains(&k) {
                        return Err(bad(
                            "k",
                            format!("between 1 and {}", crate::composite::MAX_K),
                        ));
                    }
                    link.k = Some(k);
                }
                "ready" => {
                    let n: usize = value
                        .parse()
                        .map_err(|e: std::num::ParseIntError| bad("ready", e.to_string()))?;
                    link.ready_scans = Some(n);
                }
                "token" => return Err(DeepLinkError::TokenInLink),
                _ => {}
            }
        }
        Ok(link)
    }
}

/// `%XX` escapes and `+` as a space; a malformed escape stays as it is.
fn percent_decode(s: &str) -> String {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        match bytes[i] {
            b'+' => out.push(b' '),
            b'%' if i + 2 < bytes.len() => {
                let hex = std::str::from_utf8(&bytes[i + 1..i + 3])
                    .ok()
                    .and_then(|h| u8::from_str_radix(h, 16).ok());
                match hex {
                    Some(b) => {
                        out.push(b);
                        i += 3;
                        continue;
                    }
                    None => out.push(b'%'),
                }
            }
            b => out.push(b),
        }
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::composite::Mode;

    #[test]
    fn a_render_view_reads_back_from_its_link() {
        let link = DeepLink::parse(
            "?mode=scan-colour&pose=1.5%2C-2%2C0.25%2C0%2C0%2C0%2C1&fov=55&k=3&ready=40",
        )
        .unwrap();
        assert_eq!(link.mode, Some(DisplayMode::Scans(Mode::ScanColour)));
        let pose = link.pose.unwrap();
        assert_eq!(
            pose.translation.vector,
            nalgebra::Vector3::new(1.5, -2.0, 0.25)
        );
        assert_eq!(link.fov_deg, Some(55.0));
        assert_eq!(link.k, Some(3));
        assert_eq!(link.ready_scans, Some(40));
        // Spaces (as `+` or `%20`) separate the numbers too.
        let spaced = DeepLink::parse("pose=1.5+-2%200.25+0+0+0+1").unwrap();
        assert_eq!(spaced.pose, Some(pose));
    }

    #[test]
    fn bad_values_are_named_and_tokens_refused() {
        let e = DeepLink::parse("mode=shiny").unwrap_err().to_string();
        assert!(
            e.contains("mode") && e.contains("shiny") && e.contains("blended"),
            "{e}"
        );
        let e = DeepLink::parse("pose=1,2,3").unwrap_err().to_string();
        assert!(e.contains("pose"), "{e}");
        assert!(DeepLink::parse("fov=0").is_err());
        assert!(DeepLink::parse("fov=NaN").is_err());
        assert!(DeepLink::parse("k=0").is_err());
        assert_eq!(
            DeepLink::parse("mode=best&token=s3cret"),
            Err(DeepLinkError::TokenInLink)
        );
        // Unknown keys and empty pairs are ignored.
        assert_eq!(DeepLink::parse("&&x=1&").unwrap(), DeepLink::default());
    }

    #[test]
    fn percent_decoding_keeps_what_is_not_an_escape() {
        assert_eq!(percent_decode("a%2Cb+c%"), "a,b c%");
        assert_eq!(percent_decode("%zz%4"), "%zz%4");
        assert_eq!(percent_decode("%C3%A9"), "é");
    }
}
