//! The browser viewer's files: where they are (`serve.web_dir`, else beside the
//! running executable's target directory), which request paths name them (plain
//! names only: nothing outside the directory can be named, whatever the path or its
//! links), their content types, and the page served while the viewer is not built.

use std::path::{Path, PathBuf};

/// The largest file served: the viewer's wasm is a few MiB.
const MAX_FILE: u64 = 64 * 1024 * 1024;
/// How the browser viewer is built (into `target/web`).
pub const BUILD_COMMAND: &str = "bash scripts/build-web.sh";

/// Where the browser viewer's files are when `serve.web_dir` is unset:
/// `$TEXEL_WEB_DIR`, else `web` in the target directory the daemon runs from
/// (`target/release/texeld` → `target/web`, where the build script puts it).
pub fn default_web_dir() -> Option<PathBuf> {
    if let Some(dir) = std::env::var_os("TEXEL_WEB_DIR").filter(|d| !d.is_empty()) {
        return Some(PathBuf::from(dir));
    }
    let exe = std::env::current_exe().ok()?;
    Some(exe.parent()?.parent()?.join("web"))
}

/// Whether the browser viewer is missing: no directory, or no `index.html` in it.
pub fn web_page_missing(dir: Option<&Path>) -> bool {
    dir.is_none_or(|d| !d.join("index.html").is_file())
}

/// A file found (with its length, content type and entity tag), or why none is
/// served.
pub enum Lookup {
    Found(tokio::fs::File, u64, &'static str, String),
    /// `index.html` was asked for and is not there: the viewer is not built.
    NotBuilt,
    TooLarge,
    Missing,
}

/// The file a request path names in `dir`: `/` is `index.html`; otherwise one or two
/// plain names (`[A-Za-z0-9._-]`, not starting with a dot), a regular file inside
/// `dir` even after symbolic links.
pub async fn lookup(dir: Option<&Path>, path: &str) -> Lookup {
    let Some(relative) = file_name(path) else {
        return Lookup::Missing;
    };
    let index = relative == Path::new("index.html");
    let found = match dir {
        Some(dir) => find(dir, &relative).await,
        None => Lookup::Missing,
    };
    match found {
        Lookup::Missing if index => Lookup::NotBuilt,
        found => found,
    }
}

async fn find(dir: &Path, relative: &Path) -> Lookup {
    let (Ok(root), Ok(path)) = (
        tokio::fs::canonicalize(dir).await,
        tokio::fs::canonicalize(dir.join(relative)).await,
    ) else {
        return Lookup::Missing;
    };
    // Checked before opening too: opening a FIFO would wait for a writer.
    let regular = |m: &std::fs::Metadata| m.is_file();
    if !path.starts_with(&root) || !tokio::fs::metadata(&path).await.is_ok_and(|m| regular(&m)) {
        return Lookup::Missing;
    }
    let Ok(file) = tokio::fs::File::open(&path).await else {
        return Lookup::Missing;
    };
    match file.metadata().await {
        Ok(m) if regular(&m) && m.len() > MAX_FILE => Lookup::TooLarge,
        Ok(m) if regular(&m) => {
            let tag = entity_tag(m.len(), m.modified().ok());
            Lookup::Found(file, m.len(), content_type(relative), tag)
        }
        _ => Lookup::Missing,
    }
}

/// The file's entity tag: its length and modification time. A browser that has the
/// file asks again with it and is told its copy is current (no body), so a returning
/// page reuses the wasm it fetched and compiled before; a rebuilt viewer has a new
/// time and is fetched at once.
pub fn entity_tag(len: u64, modified: Option<std::time::SystemTime>) -> String {
    let nanos = modified
        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
        .map_or(0, |d| d.as_nanos());
    format!("\"{len:x}-{nanos:x}\"")
}

/// Whether an `If-None-Match` header's value names `tag` (or is `*`).
pub fn matches_tag(if_none_match: &str, tag: &str) -> bool {
    if_none_match
        .split(',')
        .map(str::trim)
        .any(|t| t == "*" || t == tag || t.strip_prefix("W/") == Some(tag))
}

/// `/` → `index.html`; `/a.js` → `a.js`; `/assets/a.js` → `assets/a.js`; anything
/// else → `None`.
fn file_name(path: &str) -> Option<PathBuf> {
    let name = path.strip_prefix('/')?;
    let name = if name.is_empty() { "index.html" } else { name };
    let mut relative = PathBuf::new();
    for (i, part) in name.split('/').enumerate() {
        let plain = !part.is_empty()
            && part.len() <= 255
            && !part.starts_with('.')
            && part
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'));
        if i >= 2 || !plain {
            return None;
        }
        relative.push(part);
    }
    Some(relative)
}

fn content_type(path: &Path) -> &'static str {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or_default();
    match ext.to_ascii_lowercase().as_str() {
        "html" | "htm" => "text/html; charset=utf-8",
        "js" | "mjs" => "text/javascript; charset=utf-8",
        "wasm" => "application/wasm",
        "css" => "text/css; charset=utf-8",
        "json" | "map" => "application/json",
        "png" => "image/png",
        "svg" => "image/svg+xml",
        "ico" => "image/x-icon",
        "txt" => "text/plain; charset=utf-8",
        _ => "application/octet-stream",
    }
}

/// The page served in place of the viewer when it is not built.
pub fn not_built_page() -> String {
    format!(
        "<!doctype html>\n<html lang=\"en\">\n<head><meta charset=\"utf-8\">\
         <title>Texel: the browser viewer is not built</title></head>\n<body>\n\
         <h1>The browser viewer is not built</h1>\n\
         <p>This daemon serves the browser viewer from its web directory, and that has no \
         <code>index.html</code>. Build it in the source tree with</p>\n\
         <pre>{BUILD_COMMAND}</pre>\n\
         <p>which writes <code>target/web</code>, where <code>texeld</code> looks by default; \
         then reload this page. Another directory is set with <code>web_dir</code> in the \
         session's <code>[serve]</code> table.</p>\n\
         <p>Native viewers connect to this port as before.</p>\n</body>\n</html>\n"
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn entity_tags_follow_length_and_time_and_match_as_listed() {
        let t0 = std::time::UNIX_EPOCH + std::time::Duration::from_secs(1_700_000_000);
        let t1 = t0 + std::time::Duration::from_millis(1);
        let tag = entity_tag(10, Some(t0));
        assert_eq!(tag, entity_tag(10, Some(t0)));
        assert_ne!(tag, entity_tag(11, Some(t0)));
        assert_ne!(tag, entity_tag(10, Some(t1)));
        assert!(matches_tag(&tag, &tag));
        assert!(matches_tag(&format!("\"x\", W/{tag}"), &tag));
        assert!(matches_tag("*", &tag));
        assert!(!matches_tag("\"x\"", &tag));
        assert!(!matches_tag("", &tag));
    }

    #[test]
    fn only_plain_names_are_files() {
        assert_eq!(file_name("/"), Some(PathBuf::from("index.html")));
        assert_eq!(file_name("/a_b-1.wasm"), Some(PathBuf::from("a_b-1.wasm")));
        assert_eq!(
            file_name("/assets/x.js"),
            Some(PathBuf::from("assets/x.js"))
        );
        for bad in [
            "",
            "x",
            "/..",
            "/../Cargo.toml",
            "/a/../b",
            "/.env",
            "/a/b/c",
            "/a//b",
            "/%2e%2e",
            "/a\\b",
            "/a/",
        ] {
            assert_eq!(file_name(bad), None, "{bad}");
        }
    }
}
