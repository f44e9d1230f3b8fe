//! Headless rendering to PNG files: one view from a pose or an acquisition, or a
//! batch of views from a file. Deterministic: same model, camera and settings give
//! the same bytes.

use std::path::{Path, PathBuf};

use texel::Pose;
use texel::pose::parse_pose;

/// One view of a batch: where to write it, the camera pose and optionally its field
/// of view.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewSpec {
    pub out: PathBuf,
    pub world_from_eo: Pose,
    pub fov_deg: Option<f64>,
}

#[derive(Debug, thiserror::Error)]
pub enum ViewsError {
    #[error("cannot read views file {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("{path}:{line}: {message} (expected \"OUT.png x y z qx qy qz qw [fov_deg]\")")]
    Line {
        path: String,
        line: usize,
        message: String,
    },
}

/// Parses a views file: one view per line, `OUT.png x y z qx qy qz qw [fov_deg]`;
/// blank lines and lines starting with `#` are skipped.
pub fn parse_views(path: &Path) -> Result<Vec<ViewSpec>, ViewsError> {
    let display = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|source| ViewsError::Io {
        path: display.clone(),
        source,
    })?;
    parse_views_text(&text, &display)
}

pub fn parse_views_text(text: &str, origin: &str) -> Result<Vec<ViewSpec>, ViewsError> {
    let mut views = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let err = |message: String| ViewsError::Line {
            path: origin.to_string(),
            line: i + 1,
            message,
        };
        let fields: Vec<&str> = line.split_whitespace().collect();
        if fields.len() != 8 && fields.len() != 9 {
            return Err(err(format!("{} fields", fields.len())));
        }
        let world_from_eo = parse_pose(&fields[1..8].join(" ")).map_err(|e| err(e.to_string()))?;
        let fov_deg = match fields.get(8) {
            Some(f) => Some(
                f.parse::<f64>()
                    .map_err(|e| err(format!("fov {f:?}: {e}")))?,
            ),
            None => None,
        };
        views.push(ViewSpec {
            out: PathBuf::from(fields[0]),
            world_from_eo,
            fov_deg,
        });
    }
    Ok(views)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn views_parse_and_errors_name_the_line() {
        let v = parse_views_text(
            "# views\n\na.png 1 2 3 0 0 0 1\nb.png 0 0 0 0 0 0 1 40\n",
            "v.txt",
        )
        .unwrap();
        assert_eq!(v.len(), 2);
        assert_eq!(v[1].fov_deg, Some(40.0));
        let e = parse_views_text("a.png 1 2 3\n", "v.txt")
            .unwrap_err()
            .to_string();
        assert!(e.contains("v.txt:1"), "{e}");
        let e = parse_views_text("a.png 1 2 3 0 0 0 0\n", "v.txt")
            .unwrap_err()
            .to_string();
        assert!(e.contains("quaternion"), "{e}");
    }
}
