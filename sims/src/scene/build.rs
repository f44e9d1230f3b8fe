//! From a parsed scene file to a [`Scene`]: resolves paths, loads the sensor, textures
//! and meshes, checks every value, and turns objects into world-space primitives.

use std::collections::HashMap;
use std::ops::Range;
use std::path::Path;
use std::sync::Arc;

use nalgebra::{Point3, Rotation3, Vector3};
use texel::SensorModel;
use toml::Spanned;

use super::file::{HandheldFile, MaterialFile, OrbitFile, PoseFile, SceneFile, TrajectoryFile};
use super::{
    MAX_EO_SIDE, MAX_FRAMES, MAX_LIDAR_SIDE, MAX_OBJECTS, MAX_TEXTURE_SIDE, ObjectInfo, Scene,
    SceneError,
};
use crate::effects::{Effect, EffectSet};
use crate::geometry::mesh::TriMesh;
use crate::geometry::{Bvh, Primitive, Shape, parallelogram, triangle};
use crate::light::{Light, Lighting};
use crate::material::{Bricks, Material, MipImage, NoiseTable, Texture};
use crate::trajectory::{Path as TrajectoryPath, Trajectory, look_at, path_length};
use crate::world::World;

/// Turns byte offsets into lines and errors into [`SceneError`]s.
struct Ctx<'a> {
    text: &'a str,
    origin: &'a str,
    base: &'a Path,
}

impl Ctx<'_> {
    fn line(&self, offset: usize) -> usize {
        let end = offset.min(self.text.len());
        self.text.as_bytes()[..end]
            .iter()
            .filter(|&&b| b == b'\n')
            .count()
            + 1
    }

    fn err(
        &self,
        span: Option<Range<usize>>,
        key: impl Into<String>,
        message: impl Into<String>,
    ) -> SceneError {
        SceneError {
            origin: self.origin.to_string(),
            line: span.map(|s| self.line(s.start)),
            key: key.into(),
            message: message.into(),
        }
    }

    /// A TOML/serde error: its line, and the key written on that line.
    fn toml_err(&self, e: &toml::de::Error) -> SceneError {
        let span = e.span();
        let key = span
            .as_ref()
            .map(|s| self.key_on_line(s.start))
            .unwrap_or_default();
        self.err(span, key, e.message().trim().to_string())
    }

    fn key_on_line(&self, offset: usize) -> String {
        let start = self.text[..offset.min(self.text.len())]
            .rfind('\n')
            .map_or(0, |i| i + 1);
        let line = self.text[start..].lines().next().unwrap_or("").trim();
        if line.starts_with('[') {
            return line.trim_matches(|c| c == '[' || c == ']').to_string();
        }
        match line.split_once('=') {
            Some((k, _)) => k.trim().to_string(),
            None => String::new(),
        }
    }
}

fn finite(values: &[f64]) -> bool {
    values.iter().all(|v| v.is_finite())
}

fn check_color(c: &[f32; 3], max: f32) -> bool {
    c.iter().all(|v| v.is_finite() && *v >= 0.0 && *v <= max)
}

pub(super) fn build(text: &str, origin: &str, base: &Path) -> Result<Scene, SceneError> {
    let ctx = Ctx { text, origin, base };
    let file: SceneFile = toml::from_str(text).map_err(|e| ctx.toml_err(&e))?;
    let sensor = load_sensor(&ctx, &file.sensor)?;
    let effects = parse_effects(&ctx, &file.effects)?;
    let (materials, material_index) = build_materials(&ctx, &file)?;
    let (primitives, shadow_primitives, objects) = build_objects(&ctx, &file, &material_index)?;
    let lighting = build_lights(&ctx, &file)?;
    if !check_color(&file.background, 1.0e6) {
        return Err(ctx.err(
            None,
            "background",
            "colour components must be finite and >= 0",
        ));
    }
    let trajectory = build_trajectory(&ctx, &file.trajectory)?;
    let name = file.name.clone().unwrap_or_else(|| {
        Path::new(origin)
            .file_stem()
            .map_or_else(|| "scene".to_string(), |s| s.to_string_lossy().into_owned())
    });
    Ok(Scene {
        name,
        origin: origin.to_string(),
        sensor,
        effects,
        trajectory,
        objects,
        world: Arc::new(World {
            bvh: Arc::new(Bvh::new(primitives)),
            shadow_bvh: Arc::new(Bvh::new(shadow_primitives)),
            materials,
            lighting,
            background: file.background,
        }),
    })
}

fn load_sensor(ctx: &Ctx, path: &Spanned<String>) -> Result<SensorModel, SceneError> {
    let full = ctx.base.join(path.get_ref());
    let span = Some(path.span());
    let model =
        SensorModel::load(&full).map_err(|e| ctx.err(span.clone(), "sensor", e.to_string()))?;
    for (what, cam, max) in [
        ("lidar", &model.lidar, MAX_LIDAR_SIDE),
        ("eo", &model.eo, MAX_EO_SIDE),
    ] {
        if cam.width > max || cam.height > max {
            return Err(ctx.err(
                span.clone(),
                "sensor",
                format!(
                    "{}: the {what} camera is {}x{}, beyond the simulator's limit of {max} per side",
                    full.display(),
                    cam.width,
                    cam.height
                ),
            ));
        }
    }
    Ok(model)
}

fn parse_effects(ctx: &Ctx, entries: &[Spanned<toml::Value>]) -> Result<Vec<Effect>, SceneError> {
    let mut effects = Vec::with_capacity(entries.len());
    for (i, entry) in entries.iter().enumerate() {
        let e = Effect::from_toml(entry.get_ref())
            .map_err(|m| ctx.err(Some(entry.span()), format!("effects[{i}]"), m))?;
        effects.push(e);
    }
    EffectSet::from_list(&effects)
        .map_err(|m| ctx.err(entries.first().map(Spanned::span), "effects", m))?;
    Ok(effects)
}

fn build_materials(
    ctx: &Ctx,
    file: &SceneFile,
) -> Result<(Vec<Material>, HashMap<String, u32>), SceneError> {
    let mut materials = Vec::new();
    let mut index = HashMap::new();
    let mut images: HashMap<String, Arc<MipImage>> = HashMap::new();
    for (name, m) in &file.materials {
        let key = format!("materials.{name}");
        let material = build_material(ctx, &key, name, m, &mut images)?;
        index.insert(name.clone(), materials.len() as u32);
        materials.push(material);
    }
    Ok((materials, index))
}

fn build_material(
    ctx: &Ctx,
    key: &str,
    name: &str,
    spanned: &Spanned<MaterialFile>,
    images: &mut HashMap<String, Arc<MipImage>>,
) -> Result<Material, SceneError> {
    let span = Some(spanned.span());
    let m = spanned.get_ref();
    let bad = |k: &str, msg: &str| ctx.err(span.clone(), format!("{key}.{k}"), msg.to_string());
    let count = [
        m.color.is_some(),
        m.checker.is_some(),
        m.image.is_some(),
        m.noise.is_some(),
        m.bricks.is_some(),
    ]
    .iter()
    .filter(|&&b| b)
    .count();
    if count != 1 {
        return Err(ctx.err(
            span.clone(),
            key,
            "a material needs exactly one of color, checker, image, noise, bricks",
        ));
    }
    let texture = if let Some(c) = &m.color {
        if !check_color(c, 1.0) {
            return Err(bad("color", "reflectance components must be in [0, 1]"));
        }
        Texture::Constant(*c)
    } else if let Some(c) = &m.checker {
        if !(c.colors.iter().all(|col| check_color(col, 1.0)) && check_color(&c.border, 1.0)) {
            return Err(bad("checker", "colours must be in [0, 1]"));
        }
        if !(c.square_m > 0.0 && c.square_m.is_finite()) {
            return Err(bad("checker.square_m", "must be a positive length"));
        }
        if c.squares
            .is_some_and(|[x, y]| x == 0 || y == 0 || x > 10_000 || y > 10_000)
        {
            return Err(bad("checker.squares", "counts must be in 1..=10000"));
        }
        Texture::Checker {
            colors: c.colors,
            square_m: c.square_m,
            squares: c.squares,
            border: c.border,
        }
    } else if let Some(i) = &m.image {
        if !(i.size_m.iter().all(|s| *s > 0.0 && s.is_finite())) {
            return Err(bad("image.size_m", "must be two positive lengths"));
        }
        let image = load_image(ctx, key, &i.file, images)?;
        Texture::Image {
            image,
            size_m: i.size_m,
        }
    } else if let Some(n) = &m.noise {
        if n.palette.is_empty()
            || n.palette.len() > 64
            || !n.palette.iter().all(|c| check_color(c, 1.0))
        {
            return Err(bad("noise.palette", "needs 1..=64 colours in [0, 1]"));
        }
        if !(n.scale_m > 0.0 && n.scale_m.is_finite()) {
            return Err(bad("noise.scale_m", "must be a positive length"));
        }
        if !(1..=16).contains(&n.octaves) {
            return Err(bad("noise.octaves", "must be in 1..=16"));
        }
        Texture::Noise {
            palette: n.palette.clone(),
            scale_m: n.scale_m,
            octaves: n.octaves,
            table: Arc::new(NoiseTable::new(n.seed)),
        }
    } else if let Some(b) = &m.bricks {
        if !b.brick_m.iter().all(|s| *s > 0.0 && *s < 1.0e3) {
            return Err(bad(
                "bricks.brick_m",
                "must be two positive lengths [length, height] below 1000 m",
            ));
        }
        if !(b.mortar_m.is_finite()
            && b.mortar_m >= 0.0
            && b.mortar_m < b.brick_m[0].min(b.brick_m[1]))
        {
            return Err(bad(
                "bricks.mortar_m",
                "must be >= 0 and narrower than both sides of a brick",
            ));
        }
        if b.palette.is_empty()
            || b.palette.len() > 64
            || !b.palette.iter().all(|c| check_color(c, 1.0))
        {
            return Err(bad("bricks.palette", "needs 1..=64 colours in [0, 1]"));
        }
        if !(b.variation.is_finite() && (0.0..=1.0).contains(&b.variation)) {
            return Err(bad("bricks.variation", "must be in [0, 1]"));
        }
        if !check_color(&b.mortar_color, 1.0) {
            return Err(bad("bricks.mortar_color", "components must be in [0, 1]"));
        }
        Texture::Bricks(Bricks {
            brick_m: b.brick_m,
            mortar_m: b.mortar_m,
            palette: b.palette.clone(),
            variation: b.variation,
            mortar: b.mortar_color,
            seed: b.seed,
        })
    } else {
        Texture::Constant([0.5; 3])
    };
    if !(m.specular.is_finite() && (0.0..=10.0).contains(&m.specular)) {
        return Err(bad("specular", "must be in [0, 10]"));
    }
    if !(m.shininess.is_finite() && (1.0..=10_000.0).contains(&m.shininess)) {
        return Err(bad("shininess", "must be in [1, 10000]"));
    }
    if m.lidar_reflectivity
        .is_some_and(|r| !(r.is_finite() && (0.0..=1.0).contains(&r)))
    {
        return Err(bad("lidar_reflectivity", "must be in [0, 1]"));
    }
    Ok(Material {
        name: name.to_string(),
        texture,
        specular: m.specular,
        shininess: m.shininess,
        lidar_reflectivity: m.lidar_reflectivity,
    })
}

fn load_image(
    ctx: &Ctx,
    key: &str,
    file: &Spanned<String>,
    cache: &mut HashMap<String, Arc<MipImage>>,
) -> Result<Arc<MipImage>, SceneError> {
    if let Some(i) = cache.get(file.get_ref()) {
        return Ok(i.clone());
    }
    let path = ctx.base.join(file.get_ref());
    let span = Some(file.span());
    let fail = |m: String| {
        ctx.err(
            span.clone(),
            format!("{key}.image.file"),
            format!("{}: {m}", path.display()),
        )
    };
    let reader = image::ImageReader::open(&path)
        .map_err(|e| fail(format!("cannot open texture: {e}")))?
        .with_guessed_format()
        .map_err(|e| fail(format!("cannot read texture: {e}")))?;
    let (w, h) = reader
        .into_dimensions()
        .map_err(|e| fail(format!("not a readable image: {e}")))?;
    if w == 0 || h == 0 || w > MAX_TEXTURE_SIDE || h > MAX_TEXTURE_SIDE {
        return Err(fail(format!(
            "texture is {w}x{h}; sides must be in 1..={MAX_TEXTURE_SIDE}"
        )));
    }
    let decoded = image::ImageReader::open(&path)
        .map_err(|e| fail(format!("cannot open texture: {e}")))?
        .with_guessed_format()
        .map_err(|e| fail(format!("cannot read texture: {e}")))?
        .decode()
        .map_err(|e| fail(format!("cannot decode texture: {e}")))?
        .to_rgb8();
    let image = MipImage::from_srgb8(w as usize, h as usize, decoded.as_raw())
        .ok_or_else(|| fail("texture has an inconsistent size".into()))?;
    let image = Arc::new(image);
    cache.insert(file.get_ref().clone(), image.clone());
    Ok(image)
}

/// World-from-object rotation of `rotation_deg = [rx, ry, rz]`: about x, then y,
/// then z (fixed world axes), i.e. `R = Rz · Ry · Rx`.
fn rotation(deg: &[f64; 3]) -> Rotation3<f64> {
    Rotation3::from_euler_angles(
        deg[0].to_radians(),
        deg[1].to_radians(),
        deg[2].to_radians(),
    )
}

struct ObjectCtx<'a> {
    ctx: &'a Ctx<'a>,
    materials: &'a HashMap<String, u32>,
}

impl ObjectCtx<'_> {
    fn material(&self, key: &str, m: &Spanned<String>) -> Result<u32, SceneError> {
        self.materials.get(m.get_ref()).copied().ok_or_else(|| {
            let mut known: Vec<&str> = self.materials.keys().map(String::as_str).collect();
            known.sort_unstable();
            self.ctx.err(
                Some(m.span()),
                format!("{key}.material"),
                format!(
                    "unknown material {:?} (defined: {})",
                    m.get_ref(),
                    if known.is_empty() {
                        "none".to_string()
                    } else {
                        known.join(", ")
                    }
                ),
            )
        })
    }
}

type ObjectsOut = (Vec<Primitive>, Vec<Primitive>, Vec<ObjectInfo>);

fn build_objects(
    ctx: &Ctx,
    file: &SceneFile,
    materials: &HashMap<String, u32>,
) -> Result<ObjectsOut, SceneError> {
    let o = &file.objects;
    // Object ids follow the order of the objects in the file.
    let mut order: Vec<(usize, &'static str, usize)> = Vec::new();
    order.extend(
        o.plane
            .iter()
            .enumerate()
            .map(|(i, s)| (s.span().start, "plane", i)),
    );
    order.extend(
        o.boxes
            .iter()
            .enumerate()
            .map(|(i, s)| (s.span().start, "box", i)),
    );
    order.extend(
        o.sphere
            .iter()
            .enumerate()
            .map(|(i, s)| (s.span().start, "sphere", i)),
    );
    order.extend(
        o.cylinder
            .iter()
            .enumerate()
            .map(|(i, s)| (s.span().start, "cylinder", i)),
    );
    order.extend(
        o.mesh
            .iter()
            .enumerate()
            .map(|(i, s)| (s.span().start, "mesh", i)),
    );
    if order.len() > MAX_OBJECTS {
        return Err(ctx.err(None, "objects", format!("more than {MAX_OBJECTS} objects")));
    }
    order.sort_by_key(|(start, _, _)| *start);
    let oc = ObjectCtx { ctx, materials };
    let mut prims = Vec::new();
    let mut shadow_prims = Vec::new();
    let mut infos = Vec::new();
    for (id, (_, kind, i)) in order.into_iter().enumerate() {
        let id = id as u32;
        let key = format!("objects.{kind}[{i}]");
        let first = prims.len();
        let (name, casts) = match kind {
            "plane" => (
                plane(&oc, &key, &o.plane[i], id, &mut prims)?,
                o.plane[i].get_ref().casts_shadows,
            ),
            "box" => (
                cuboid(&oc, &key, &o.boxes[i], id, &mut prims)?,
                o.boxes[i].get_ref().casts_shadows,
            ),
            "sphere" => (
                sphere(&oc, &key, &o.sphere[i], id, &mut prims)?,
                o.sphere[i].get_ref().casts_shadows,
            ),
            "cylinder" => (
                cylinder(&oc, &key, &o.cylinder[i], id, &mut prims)?,
                o.cylinder[i].get_ref().casts_shadows,
            ),
            _ => (
                mesh(&oc, &key, &o.mesh[i], id, &mut prims)?,
                o.mesh[i].get_ref().casts_shadows,
            ),
        };
        if casts {
            shadow_prims.extend_from_slice(&prims[first..]);
        }
        infos.push(ObjectInfo {
            kind,
            name: name.unwrap_or(key),
        });
    }
    Ok((prims, shadow_prims, infos))
}

fn check_pose(
    oc: &ObjectCtx,
    key: &str,
    span: Range<usize>,
    position: &[f64; 3],
    rotation_deg: &[f64; 3],
) -> Result<(), SceneError> {
    if !finite(position) || !finite(rotation_deg) {
        return Err(oc
            .ctx
            .err(Some(span), key, "position and rotation_deg must be finite"));
    }
    Ok(())
}

fn positive(
    oc: &ObjectCtx,
    key: &str,
    span: Range<usize>,
    what: &str,
    values: &[f64],
) -> Result<(), SceneError> {
    if values
        .iter()
        .all(|v| v.is_finite() && *v > 0.0 && *v < 1.0e7)
    {
        Ok(())
    } else {
        Err(oc.ctx.err(
            Some(span),
            format!("{key}.{what}"),
            "must be positive, finite lengths (m)",
        ))
    }
}

fn plane(
    oc: &ObjectCtx,
    key: &str,
    s: &Spanned<super::file::PlaneFile>,
    id: u32,
    out: &mut Vec<Primitive>,
) -> Result<Option<String>, SceneError> {
    let p = s.get_ref();
    check_pose(oc, key, s.span(), &p.position, &p.rotation_deg)?;
    let material = oc.material(key, &p.material)?;
    let r = rotation(&p.rotation_deg);
    let (ax, ay, az) = (r * Vector3::x(), r * Vector3::y(), r * Vector3::z());
    let pos = Point3::from(p.position);
    match p.size {
        Some(size) => {
            positive(oc, key, s.span(), "size", &size)?;
            let (eu, ev) = (ax * size[0], ay * size[1]);
            let corner = pos - eu * 0.5 - ev * 0.5;
            out.extend(parallelogram(corner, eu, ev, id, material));
        }
        None => out.push(Primitive {
            shape: Shape::InfinitePlane {
                origin: pos,
                axis_u: ax,
                axis_v: ay,
                normal: az,
            },
            object: id,
            material,
        }),
    }
    Ok(p.name.clone())
}

fn cuboid(
    oc: &ObjectCtx,
    key: &str,
    s: &Spanned<super::file::BoxFile>,
    id: u32,
    out: &mut Vec<Primitive>,
) -> Result<Option<String>, SceneError> {
    let b = s.get_ref();
    check_pose(oc, key, s.span(), &b.position, &b.rotation_deg)?;
    positive(oc, key, s.span(), "size", &b.size)?;
    let material = oc.material(key, &b.material)?;
    let r = rotation(&b.rotation_deg);
    let axes = [r * Vector3::x(), r * Vector3::y(), r * Vector3::z()];
    let pos = Point3::from(b.position);
    for a in 0..3 {
        let (bi, ci) = ((a + 1) % 3, (a + 2) % 3);
        for sign in [1.0, -1.0] {
            let centre = pos + axes[a] * (sign * 0.5 * b.size[a]);
            let (eb, ec) = (axes[bi] * b.size[bi], axes[ci] * b.size[ci]);
            // Outward normal: eb × ec points along +axes[a].
            let (eu, ev) = if sign > 0.0 { (eb, ec) } else { (ec, eb) };
            out.extend(parallelogram(
                centre - eu * 0.5 - ev * 0.5,
                eu,
                ev,
                id,
                material,
            ));
        }
    }
    Ok(b.name.clone())
}

fn sphere(
    oc: &ObjectCtx,
    key: &str,
    s: &Spanned<super::file::SphereFile>,
    id: u32,
    out: &mut Vec<Primitive>,
) -> Result<Option<String>, SceneError> {
    let p = s.get_ref();
    check_pose(oc, key, s.span(), &p.position, &p.rotation_deg)?;
    positive(oc, key, s.span(), "radius", &[p.radius])?;
    let material = oc.material(key, &p.material)?;
    let r = rotation(&p.rotation_deg);
    out.push(Primitive {
        shape: Shape::Sphere {
            center: Point3::from(p.position),
            radius: p.radius,
            axis_x: r * Vector3::x(),
            axis_y: r * Vector3::y(),
            axis_z: r * Vector3::z(),
        },
        object: id,
        material,
    });
    Ok(p.name.clone())
}

fn cylinder(
    oc: &ObjectCtx,
    key: &str,
    s: &Spanned<super::file::CylinderFile>,
    id: u32,
    out: &mut Vec<Primitive>,
) -> Result<Option<String>, SceneError> {
    let c = s.get_ref();
    check_pose(oc, key, s.span(), &c.position, &c.rotation_deg)?;
    positive(oc, key, s.span(), "radius", &[c.radius])?;
    positive(oc, key, s.span(), "height", &[c.height])?;
    let material = oc.material(key, &c.material)?;
    let r = rotation(&c.rotation_deg);
    out.push(Primitive {
        shape: Shape::Cylinder {
            center: Point3::from(c.position),
            radius: c.radius,
            half_height: 0.5 * c.height,
            axis_x: r * Vector3::x(),
            axis_y: r * Vector3::y(),
            axis_z: r * Vector3::z(),
        },
        object: id,
        material,
    });
    Ok(c.name.clone())
}

fn mesh(
    oc: &ObjectCtx,
    key: &str,
    s: &Spanned<super::file::MeshFile>,
    id: u32,
    out: &mut Vec<Primitive>,
) -> Result<Option<String>, SceneError> {
    let m = s.get_ref();
    check_pose(oc, key, s.span(), &m.position, &m.rotation_deg)?;
    positive(oc, key, s.span(), "scale", &[m.scale])?;
    let material = oc.material(key, &m.material)?;
    let path = oc.ctx.base.join(m.file.get_ref());
    let tri = TriMesh::load(&path).map_err(|e| {
        oc.ctx
            .err(Some(m.file.span()), format!("{key}.file"), e.to_string())
    })?;
    let r = rotation(&m.rotation_deg);
    let pos = Point3::from(m.position);
    let world = |p: [f64; 3]| pos + r * (Vector3::from(p) * m.scale);
    for (t, tri_idx) in tri.triangles.iter().enumerate() {
        let [a, b, c] = tri_idx.map(|i| tri.positions[i as usize]);
        let uv = match &tri.triangle_uvs {
            Some(uvs) => uvs[t].map(|i| tri.uvs.get(i as usize).copied().unwrap_or([0.0; 2])),
            None => [a, b, c].map(|p| [p[0] * m.scale, p[1] * m.scale]),
        };
        out.extend(triangle([world(a), world(b), world(c)], uv, id, material));
    }
    Ok(m.name.clone())
}

fn build_lights(ctx: &Ctx, file: &SceneFile) -> Result<Lighting, SceneError> {
    let l = &file.lights;
    if !check_color(&l.ambient, 1.0e6) {
        return Err(ctx.err(None, "lights.ambient", "components must be finite and >= 0"));
    }
    let mut lights = Vec::new();
    for (i, d) in l.directional.iter().enumerate() {
        let key = format!("lights.directional[{i}]");
        let v = d.get_ref();
        let dir = Vector3::from(v.direction);
        let n = dir.norm();
        if !(n > 0.0 && n.is_finite()) {
            return Err(ctx.err(
                Some(d.span()),
                format!("{key}.direction"),
                "must be a non-zero finite vector",
            ));
        }
        if !(check_color(&v.color, 1.0e6) && v.intensity.is_finite() && v.intensity >= 0.0) {
            return Err(ctx.err(
                Some(d.span()),
                key,
                "color and intensity must be finite and >= 0",
            ));
        }
        lights.push(Light::Directional {
            towards_light: -dir / n,
            color: v.color,
            intensity: v.intensity,
            shadows: v.shadows,
        });
    }
    for (i, p) in l.point.iter().enumerate() {
        let key = format!("lights.point[{i}]");
        let v = p.get_ref();
        if !finite(&v.position) {
            return Err(ctx.err(Some(p.span()), format!("{key}.position"), "must be finite"));
        }
        if !(check_color(&v.color, 1.0e6) && v.intensity.is_finite() && v.intensity >= 0.0) {
            return Err(ctx.err(
                Some(p.span()),
                key,
                "color and intensity must be finite and >= 0",
            ));
        }
        lights.push(Light::Point {
            position: Point3::from(v.position),
            color: v.color,
            intensity: v.intensity,
            shadows: v.shadows,
        });
    }
    Ok(Lighting {
        ambient: l.ambient,
        lights,
    })
}

fn build_trajectory(
    ctx: &Ctx,
    spanned: &Spanned<TrajectoryFile>,
) -> Result<Trajectory, SceneError> {
    let t = spanned.get_ref();
    let span = Some(spanned.span());
    if !(t.rate_hz.is_finite() && t.rate_hz > 0.0 && t.rate_hz <= 10_000.0) {
        return Err(ctx.err(span, "trajectory.rate_hz", "must be in (0, 10000] Hz"));
    }
    if !(t.start_time_s.is_finite() && (0.0..=1.0e9).contains(&t.start_time_s)) {
        return Err(ctx.err(span, "trajectory.start_time_s", "must be in [0, 1e9] s"));
    }
    let kinds = [t.orbit.is_some(), t.handheld.is_some(), t.poses.is_some()];
    if kinds.iter().filter(|&&b| b).count() != 1 {
        return Err(ctx.err(
            span,
            "trajectory",
            "needs exactly one of orbit, handheld, poses",
        ));
    }
    let frames_given = t.frames.as_ref().map(|f| (*f.get_ref(), f.span()));
    if let Some((n, s)) = &frames_given
        && (*n == 0 || *n > MAX_FRAMES)
    {
        return Err(ctx.err(
            Some(s.clone()),
            "trajectory.frames",
            format!("must be in 1..={MAX_FRAMES}"),
        ));
    }
    let (path, frames) = if let Some(o) = &t.orbit {
        let frames = frames_given
            .as_ref()
            .map(|(n, _)| *n as usize)
            .ok_or_else(|| ctx.err(span.clone(), "trajectory.frames", "an orbit needs `frames`"))?;
        (orbit(ctx, o, frames)?, frames)
    } else if let Some(h) = &t.handheld {
        let (path, natural) = handheld(ctx, h, t.rate_hz)?;
        (
            path,
            frames_given.as_ref().map_or(natural, |(n, _)| *n as usize),
        )
    } else if let Some(p) = &t.poses {
        let poses = explicit_poses(ctx, p)?;
        let frames = match &frames_given {
            Some((n, s)) if *n as usize > poses.len() => {
                return Err(ctx.err(
                    Some(s.clone()),
                    "trajectory.frames",
                    format!("{n} frames but only {} poses", poses.len()),
                ));
            }
            Some((n, _)) => *n as usize,
            None => poses.len(),
        };
        (TrajectoryPath::Poses(poses), frames)
    } else {
        return Err(ctx.err(
            span,
            "trajectory",
            "needs exactly one of orbit, handheld, poses",
        ));
    };
    Ok(Trajectory {
        path,
        rate_hz: t.rate_hz,
        frames,
        start_time_ns: (t.start_time_s * 1.0e9).round() as u64,
    })
}

fn orbit(ctx: &Ctx, o: &Spanned<OrbitFile>, frames: usize) -> Result<TrajectoryPath, SceneError> {
    let v = o.get_ref();
    let look = v.look_at.unwrap_or(v.center);
    if !finite(&v.center) || !finite(&look) || !finite(&[v.height_m, v.start_deg, v.arc_deg]) {
        return Err(ctx.err(Some(o.span()), "trajectory.orbit", "values must be finite"));
    }
    if !(v.radius_m.is_finite() && v.radius_m > 0.0) {
        return Err(ctx.err(
            Some(o.span()),
            "trajectory.orbit.radius_m",
            "must be positive",
        ));
    }
    Ok(TrajectoryPath::Orbit {
        center: Point3::from(v.center),
        radius_m: v.radius_m,
        height_m: v.height_m,
        look_at: Point3::from(look),
        start_deg: v.start_deg,
        arc_deg: v.arc_deg,
        period_frames: frames,
    })
}

fn handheld(
    ctx: &Ctx,
    h: &Spanned<HandheldFile>,
    rate_hz: f64,
) -> Result<(TrajectoryPath, usize), SceneError> {
    let v = h.get_ref();
    let key = "trajectory.handheld";
    if v.waypoints.is_empty()
        || v.waypoints.len() > 100_000
        || !v.waypoints.iter().all(|w| finite(w))
    {
        return Err(ctx.err(
            Some(h.span()),
            format!("{key}.waypoints"),
            "needs 1..=100000 finite points",
        ));
    }
    if v.look_at.is_some_and(|l| !finite(&l)) {
        return Err(ctx.err(Some(h.span()), format!("{key}.look_at"), "must be finite"));
    }
    if !(v.speed_m_per_s.is_finite() && v.speed_m_per_s > 0.0) {
        return Err(ctx.err(
            Some(h.span()),
            format!("{key}.speed_m_per_s"),
            "must be positive",
        ));
    }
    if !(v.jitter_position_m.is_finite()
        && v.jitter_position_m >= 0.0
        && v.jitter_rotation_deg.is_finite()
        && v.jitter_rotation_deg >= 0.0)
    {
        return Err(ctx.err(Some(h.span()), key, "jitter values must be finite and >= 0"));
    }
    if let Some(pan) = v.pan
        && !(pan.amplitude_deg.is_finite()
            && (0.0..=180.0).contains(&pan.amplitude_deg)
            && pan.period_s.is_finite()
            && pan.period_s >= 0.1
            && pan.phase_deg.is_finite())
    {
        return Err(ctx.err(
            Some(h.span()),
            format!("{key}.pan"),
            "needs amplitude_deg in [0, 180], period_s of at least 0.1 and a finite phase_deg",
        ));
    }
    if !(v.pitch_deg.is_finite() && v.pitch_deg.abs() <= 85.0) {
        return Err(ctx.err(
            Some(h.span()),
            format!("{key}.pitch_deg"),
            "must be in [-85, 85] degrees",
        ));
    }
    let waypoints: Vec<Point3<f64>> = v.waypoints.iter().map(|w| Point3::from(*w)).collect();
    let seconds = path_length(&waypoints) / v.speed_m_per_s;
    let natural = (seconds * rate_hz).floor() + 1.0;
    if !(natural.is_finite() && natural <= MAX_FRAMES as f64) {
        return Err(ctx.err(
            Some(h.span()),
            key,
            format!("the walk is longer than {MAX_FRAMES} frames"),
        ));
    }
    Ok((
        TrajectoryPath::Handheld {
            waypoints,
            look_at: v.look_at.map(Point3::from),
            speed_m_per_s: v.speed_m_per_s,
            jitter_position_m: v.jitter_position_m,
            jitter_rotation_deg: v.jitter_rotation_deg,
            seed: v.seed,
            pan_amplitude_deg: v.pan.map_or(0.0, |p| p.amplitude_deg),
            pan_period_s: v.pan.map_or(1.0, |p| p.period_s),
            pan_phase_deg: v.pan.map_or(0.0, |p| p.phase_deg),
            pitch_deg: v.pitch_deg,
        },
        natural as usize,
    ))
}

fn explicit_poses(
    ctx: &Ctx,
    poses: &Spanned<Vec<Spanned<PoseFile>>>,
) -> Result<Vec<texel::Pose>, SceneError> {
    if poses.get_ref().is_empty() || poses.get_ref().len() as u64 > MAX_FRAMES {
        return Err(ctx.err(
            Some(poses.span()),
            "trajectory.poses",
            format!("needs 1..={MAX_FRAMES} poses"),
        ));
    }
    let mut out = Vec::with_capacity(poses.get_ref().len());
    for (i, p) in poses.get_ref().iter().enumerate() {
        let key = format!("trajectory.poses[{i}]");
        let v = p.get_ref();
        let pose = match (v.rotation_xyzw, v.look_at) {
            (Some(q), None) => texel::pose::pose_from_parts(v.position, q)
                .map_err(|e| ctx.err(Some(p.span()), &key, e.to_string()))?,
            (None, Some(target)) => {
                if !finite(&v.position) || !finite(&target) || !v.roll_deg.is_finite() {
                    return Err(ctx.err(Some(p.span()), &key, "values must be finite"));
                }
                look_at(Point3::from(v.position), Point3::from(target), Vector3::z())
                    * nalgebra::UnitQuaternion::from_axis_angle(
                        &Vector3::z_axis(),
                        v.roll_deg.to_radians(),
                    )
            }
            _ => {
                return Err(ctx.err(
                    Some(p.span()),
                    &key,
                    "needs exactly one of rotation_xyzw, look_at",
                ));
            }
        };
        out.push(pose);
    }
    Ok(out)
}
