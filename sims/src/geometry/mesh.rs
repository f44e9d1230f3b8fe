//! Triangle meshes from Wavefront OBJ (`v`, `vt`, `f`; polygons fan-triangulated) and
//! PLY (ascii or binary little/big endian; `x y z`, optional `u v`/`s t`, face
//! `vertex_indices`). Every count is checked against [`MAX_MESH_ELEMENTS`] before
//! anything is allocated for it, and every index against the vertex count.

use std::path::Path;

use thiserror::Error;

/// Most vertices, texture coordinates or triangles a mesh may have.
pub const MAX_MESH_ELEMENTS: usize = 4_000_000;
/// Largest mesh file read (bytes).
pub const MAX_MESH_FILE_BYTES: u64 = 512 << 20;

/// A triangle mesh in its own coordinates.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TriMesh {
    pub positions: Vec<[f64; 3]>,
    pub uvs: Vec<[f64; 2]>,
    /// Position indices per triangle.
    pub triangles: Vec<[u32; 3]>,
    /// Texture-coordinate indices per triangle, when every face has them.
    pub triangle_uvs: Option<Vec<[u32; 3]>>,
}

#[derive(Debug, Error)]
pub enum MeshError {
    #[error("cannot read mesh {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("mesh {path} is {bytes} bytes, more than the {MAX_MESH_FILE_BYTES}-byte limit")]
    TooLarge { path: String, bytes: u64 },
    #[error("mesh {path}: {message}")]
    Invalid { path: String, message: String },
    #[error("mesh {path}: unknown format (expected a .obj or .ply file)")]
    UnknownFormat { path: String },
}

impl TriMesh {
    /// Reads an OBJ or PLY file, chosen by extension.
    pub fn load(path: &Path) -> Result<Self, MeshError> {
        let name = path.display().to_string();
        let meta = std::fs::metadata(path).map_err(|source| MeshError::Io {
            path: name.clone(),
            source,
        })?;
        if meta.len() > MAX_MESH_FILE_BYTES {
            return Err(MeshError::TooLarge {
                path: name,
                bytes: meta.len(),
            });
        }
        let bytes = std::fs::read(path).map_err(|source| MeshError::Io {
            path: name.clone(),
            source,
        })?;
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        let invalid = |message: String| MeshError::Invalid {
            path: name.clone(),
            message,
        };
        match ext.as_deref() {
            Some("obj") => parse_obj(&String::from_utf8_lossy(&bytes)).map_err(invalid),
            Some("ply") => parse_ply(&bytes).map_err(invalid),
            _ => Err(MeshError::UnknownFormat { path: name }),
        }
    }
}

fn check_count(what: &str, n: usize) -> Result<(), String> {
    if n > MAX_MESH_ELEMENTS {
        return Err(format!("more than {MAX_MESH_ELEMENTS} {what} (the limit)"));
    }
    Ok(())
}

fn parse_f64(token: Option<&str>, line: usize) -> Result<f64, String> {
    let t = token.ok_or_else(|| format!("line {line}: missing number"))?;
    let v: f64 = t
        .parse()
        .map_err(|_| format!("line {line}: {t:?} is not a number"))?;
    if !v.is_finite() {
        return Err(format!("line {line}: {t:?} is not finite"));
    }
    Ok(v)
}

/// Resolves an OBJ index (1-based, or negative from the end) against `len` items.
fn obj_index(token: &str, len: usize, line: usize) -> Result<u32, String> {
    let i: i64 = token
        .parse()
        .map_err(|_| format!("line {line}: bad index {token:?}"))?;
    let resolved = if i > 0 {
        i - 1
    } else if i < 0 {
        len as i64 + i
    } else {
        -1
    };
    if resolved < 0 || resolved >= len as i64 {
        return Err(format!(
            "line {line}: index {i} is outside the {len} items defined so far"
        ));
    }
    Ok(resolved as u32)
}

/// Parses OBJ text.
pub fn parse_obj(text: &str) -> Result<TriMesh, String> {
    let mut mesh = TriMesh::default();
    let mut face_uvs: Vec<[u32; 3]> = Vec::new();
    let mut all_faces_have_uv = true;
    for (n, raw) in text.lines().enumerate() {
        let line = n + 1;
        let mut tokens = raw.split_whitespace();
        match tokens.next() {
            Some("v") => {
                check_count("vertices", mesh.positions.len() + 1)?;
                mesh.positions.push([
                    parse_f64(tokens.next(), line)?,
                    parse_f64(tokens.next(), line)?,
                    parse_f64(tokens.next(), line)?,
                ]);
            }
            Some("vt") => {
                check_count("texture coordinates", mesh.uvs.len() + 1)?;
                mesh.uvs.push([
                    parse_f64(tokens.next(), line)?,
                    parse_f64(tokens.next(), line)?,
                ]);
            }
            Some("f") => {
                let mut pos = Vec::with_capacity(4);
                let mut uv = Vec::with_capacity(4);
                for corner in tokens {
                    if pos.len() >= 256 {
                        return Err(format!("line {line}: face with more than 256 corners"));
                    }
                    let mut parts = corner.split('/');
                    let p = parts.next().unwrap_or("");
                    pos.push(obj_index(p, mesh.positions.len(), line)?);
                    match parts.next() {
                        Some(t) if !t.is_empty() => uv.push(obj_index(t, mesh.uvs.len(), line)?),
                        _ => all_faces_have_uv = false,
                    }
                }
                if pos.len() < 3 {
                    return Err(format!("line {line}: a face needs at least 3 corners"));
                }
                for k in 1..pos.len() - 1 {
                    check_count("triangles", mesh.triangles.len() + 1)?;
                    mesh.triangles.push([pos[0], pos[k], pos[k + 1]]);
                    if uv.len() == pos.len() {
                        face_uvs.push([uv[0], uv[k], uv[k + 1]]);
                    }
                }
            }
            _ => {}
        }
    }
    if mesh.triangles.is_empty() {
        return Err("no faces".into());
    }
    if all_faces_have_uv && face_uvs.len() == mesh.triangles.len() {
        mesh.triangle_uvs = Some(face_uvs);
    }
    Ok(mesh)
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum PlyFormat {
    Ascii,
    BinaryLe,
    BinaryBe,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum PlyType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl PlyType {
    fn parse(name: &str) -> Option<Self> {
        Some(match name {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }
}

#[derive(Debug, Clone)]
enum PlyProperty {
    Scalar(String, PlyType),
    List(String, PlyType, PlyType),
}

#[derive(Debug, Clone)]
struct PlyElement {
    name: String,
    count: usize,
    properties: Vec<PlyProperty>,
}

/// Reads values of a PLY body, ascii or binary.
struct PlyBody<'a> {
    format: PlyFormat,
    bytes: &'a [u8],
    pos: usize,
    tokens: std::str::SplitAsciiWhitespace<'a>,
}

impl PlyBody<'_> {
    fn read(&mut self, t: PlyType) -> Result<f64, String> {
        if self.format == PlyFormat::Ascii {
            let tok = self.tokens.next().ok_or("the body ends early")?;
            return tok
                .parse::<f64>()
                .map_err(|_| format!("{tok:?} is not a number"));
        }
        let n = t.size();
        let end = self.pos + n;
        let b = self.bytes.get(self.pos..end).ok_or("the body ends early")?;
        self.pos = end;
        let mut a = [0u8; 8];
        a[..n].copy_from_slice(b);
        if self.format == PlyFormat::BinaryBe {
            a[..n].reverse();
        }
        Ok(match t {
            PlyType::I8 => f64::from(a[0] as i8),
            PlyType::U8 => f64::from(a[0]),
            PlyType::I16 => f64::from(i16::from_le_bytes([a[0], a[1]])),
            PlyType::U16 => f64::from(u16::from_le_bytes([a[0], a[1]])),
            PlyType::I32 => f64::from(i32::from_le_bytes([a[0], a[1], a[2], a[3]])),
            PlyType::U32 => f64::from(u32::from_le_bytes([a[0], a[1], a[2], a[3]])),
            PlyType::F32 => f64::from(f32::from_le_bytes([a[0], a[1], a[2], a[3]])),
            PlyType::F64 => f64::from_le_bytes(a),
        })
    }
}

/// Parses a PLY file's bytes.
pub fn parse_ply(bytes: &[u8]) -> Result<TriMesh, String> {
    const END: &[u8] = b"end_header";
    let header_end = bytes
        .windows(END.len())
        .take(64 * 1024)
        .position(|w| w == END)
        .ok_or("no end_header in the first 64 KiB")?;
    let mut body_start = header_end + END.len();
    // The header line ends with \n (or \r\n).
    while body_start < bytes.len() && bytes[body_start] != b'\n' {
        body_start += 1;
    }
    body_start += 1;
    let header = String::from_utf8_lossy(&bytes[..header_end]);
    let mut lines = header.lines();
    if lines.next().map(str::trim) != Some("ply") {
        return Err("does not start with \"ply\"".into());
    }
    let mut format = None;
    let mut elements: Vec<PlyElement> = Vec::new();
    for line in lines {
        let t: Vec<&str> = line.split_whitespace().collect();
        match t.as_slice() {
            ["format", f, _] => {
                format = Some(match *f {
                    "ascii" => PlyFormat::Ascii,
                    "binary_little_endian" => PlyFormat::BinaryLe,
                    "binary_big_endian" => PlyFormat::BinaryBe,
                    other => return Err(format!("unknown format {other:?}")),
                })
            }
            ["element", name, count] => {
                let count: usize = count
                    .parse()
                    .map_err(|_| format!("element {name}: bad count {count:?}"))?;
                check_count(name, count)?;
                elements.push(PlyElement {
                    name: name.to_string(),
                    count,
                    properties: Vec::new(),
                });
            }
            ["property", "list", ct, it, name] => {
                let e = elements.last_mut().ok_or("property before any element")?;
                let (Some(c), Some(i)) = (PlyType::parse(ct), PlyType::parse(it)) else {
                    return Err(format!("property {name}: unknown type"));
                };
                e.properties.push(PlyProperty::List(name.to_string(), c, i));
            }
            ["property", ty, name] => {
                let e = elements.last_mut().ok_or("property before any element")?;
                let ty = PlyType::parse(ty).ok_or(format!("property {name}: unknown type {ty}"))?;
                e.properties.push(PlyProperty::Scalar(name.to_string(), ty));
            }
            _ => {}
        }
    }
    let format = format.ok_or("no format line")?;
    let body = bytes.get(body_start..).unwrap_or(&[]);
    let text = if format == PlyFormat::Ascii {
        std::str::from_utf8(body).map_err(|_| "ascii body is not text")?
    } else {
        ""
    };
    let mut reader = PlyBody {
        format,
        bytes: body,
        pos: 0,
        tokens: text.split_ascii_whitespace(),
    };
    let mut mesh = TriMesh::default();
    for e in &elements {
        match e.name.as_str() {
            "vertex" => read_vertices(e, &mut reader, &mut mesh)?,
            "face" => read_faces(e, &mut reader, &mut mesh)?,
            _ => skip_element(e, &mut reader)?,
        }
    }
    if mesh.triangles.is_empty() {
        return Err("no faces".into());
    }
    if !mesh.uvs.is_empty() {
        mesh.triangle_uvs = Some(mesh.triangles.clone());
    }
    Ok(mesh)
}

fn read_vertices(e: &PlyElement, r: &mut PlyBody, mesh: &mut TriMesh) -> Result<(), String> {
    let find = |names: &[&str]| {
        e.properties
            .iter()
            .position(|p| matches!(p, PlyProperty::Scalar(n, _) if names.contains(&n.as_str())))
    };
    let (Some(ix), Some(iy), Some(iz)) = (find(&["x"]), find(&["y"]), find(&["z"])) else {
        return Err("vertex element lacks x, y or z".into());
    };
    let iu = find(&["u", "s", "texture_u"]);
    let iv = find(&["v", "t", "texture_v"]);
    let has_uv = iu.is_some() && iv.is_some();
    mesh.positions.reserve(e.count);
    if has_uv {
        mesh.uvs.reserve(e.count);
    }
    let mut values = vec![0.0; e.properties.len()];
    for k in 0..e.count {
        for (slot, p) in values.iter_mut().zip(&e.properties) {
            *slot = match p {
                PlyProperty::Scalar(_, t) => r.read(*t)?,
                PlyProperty::List(_, ct, it) => {
                    let n = r.read(*ct)? as usize;
                    for _ in 0..n.min(1 << 16) {
                        r.read(*it)?;
                    }
                    0.0
                }
            };
        }
        let p = [values[ix], values[iy], values[iz]];
        if p.iter().any(|c| !c.is_finite()) {
            return Err(format!("vertex {k} is not finite"));
        }
        mesh.positions.push(p);
        if let (Some(iu), Some(iv)) = (iu, iv) {
            mesh.uvs.push([values[iu], values[iv]]);
        }
    }
    Ok(())
}

fn read_faces(e: &PlyElement, r: &mut PlyBody, mesh: &mut TriMesh) -> Result<(), String> {
    let nverts = mesh.positions.len();
    for k in 0..e.count {
        for p in &e.properties {
            match p {
                PlyProperty::List(name, ct, it)
                    if name == "vertex_indices" || name == "vertex_index" =>
                {
                    let n = r.read(*ct)?;
                    if !(3.0..=256.0).contains(&n) {
                        return Err(format!("face {k} has {n} corners (3..=256 allowed)"));
                    }
                    let mut corners = Vec::with_capacity(n as usize);
                    for _ in 0..n as usize {
                        let i = r.read(*it)?;
                        if !(i >= 0.0 && (i as usize) < nverts) {
                            return Err(format!(
                                "face {k} refers to vertex {i}, but there are {nverts}"
                            ));
                        }
                        corners.push(i as u32);
                    }
                    for c in 1..corners.len() - 1 {
                        check_count("triangles", mesh.triangles.len() + 1)?;
                        mesh.triangles
                            .push([corners[0], corners[c], corners[c + 1]]);
                    }
                }
                PlyProperty::List(_, ct, it) => {
                    let n = r.read(*ct)? as usize;
                    for _ in 0..n.min(1 << 16) {
                        r.read(*it)?;
                    }
                }
                PlyProperty::Scalar(_, t) => {
                    r.read(*t)?;
                }
            }
        }
    }
    Ok(())
}

fn skip_element(e: &PlyElement, r: &mut PlyBody) -> Result<(), String> {
    for _ in 0..e.count {
        for p in &e.properties {
            match p {
                PlyProperty::Scalar(_, t) => {
                    r.read(*t)?;
                }
                PlyProperty::List(_, ct, it) => {
                    let n = r.read(*ct)? as usize;
                    for _ in 0..n.min(1 << 16) {
                        r.read(*it)?;
                    }
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn obj_quads_become_triangles_with_uvs() {
        let m = parse_obj(
            "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1 2/2 3/3 4/4\n",
        )
        .unwrap();
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        assert_eq!(m.triangle_uvs, Some(vec![[0, 1, 2], [0, 2, 3]]));
        assert!(
            parse_obj("v 0 0 0\nf 1 2 3\n")
                .unwrap_err()
                .contains("line 2")
        );
        assert!(parse_obj("v 0 0 nan\n").is_err());
    }

    #[test]
    fn ply_ascii_and_binary_agree() {
        let ascii = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";
        let a = parse_ply(ascii).unwrap();
        let mut bin = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n".to_vec();
        for v in [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]] {
            for c in v {
                bin.extend_from_slice(&c.to_le_bytes());
            }
        }
        bin.push(3);
        for i in [0i32, 1, 2] {
            bin.extend_from_slice(&i.to_le_bytes());
        }
        let b = parse_ply(&bin).unwrap();
        assert_eq!(a, b);
        assert_eq!(a.triangles, vec![[0, 1, 2]]);
        // Truncated and out-of-range bodies are errors, not panics.
        assert!(parse_ply(&bin[..bin.len() - 3]).is_err());
        let bad = String::from_utf8_lossy(ascii).replace("3 0 1 2", "3 0 1 7");
        assert!(parse_ply(bad.as_bytes()).unwrap_err().contains("vertex 7"));
        let huge = String::from_utf8_lossy(ascii).replace("vertex 3", "vertex 99999999999");
        assert!(parse_ply(huge.as_bytes()).is_err());
    }
}
