//! The prepared VDTM model on the GPU: the surface's polygons in draw order (holes
//! first, then the ones one view sees, then the ones with view maps), the views'
//! images as one texture array, each view's pose and calibrated camera, and the
//! per-polygon blend buffer that each frame rewrites for the polygons whose views
//! depend on the eye (§8: the view maps are queried once per polygon per frame).

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, UVec4, Vec4};
use nalgebra::{Point3, Translation3};
use texel::camera::Distortion;
use texel::{PinholeCamera, Pose};
use texel_vdtm::Texturing;

use super::prepare::PreparedVdtm;
use crate::gpu::{EO_FORMAT, GpuError, gpu_from_pose_relative, rgba_of_rgb};

/// A vertex of the surface (`VdtmIn` in `vdtm.wgsl`): position relative to the
/// model's origin, the hole colour (display values) and the polygon's draw slot.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub(crate) struct VdtmVertex {
    pub position: [f32; 3],
    pub colour: [u8; 4],
    pub polygon: u32,
}

pub(crate) const VDTM_VERTEX_ATTRIBUTES: [wgpu::VertexAttribute; 3] =
    wgpu::vertex_attr_array![0 => Float32x3, 1 => Unorm8x4, 2 => Uint32];

/// `EoView` in `vdtm.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub(crate) struct EoViewUniform {
    pub eo_from_model: Mat4,
    pub centre_model: Vec4,
    pub intrinsics: Vec4,
    pub shape: Vec4,
    pub distortion: Vec4,
    pub distortion_k3: Vec4,
}

/// `PolygonBlend` in `vdtm.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct PolygonBlend {
    pub views: UVec4,
    pub weights: Vec4,
}

const BLEND_BYTES: u64 = std::mem::size_of::<PolygonBlend>() as u64;

/// The prepared model uploaded.
pub struct GpuVdtm {
    pub(crate) vertices: wgpu::Buffer,
    pub(crate) views: wgpu::Buffer,
    pub(crate) blends: wgpu::Buffer,
    pub(crate) images: wgpu::TextureView,
    /// Per draw slot, the model's polygon.
    slots: Vec<u32>,
    /// Draw slots `[0, holes)` are holes, `[holes, mapped_from)` one view's,
    /// `[mapped_from, ..)` view-mapped.
    pub(crate) holes: u32,
    mapped_from: usize,
    /// The blends of the view-mapped slots, rewritten each frame.
    scratch: Vec<PolygonBlend>,
    pub(crate) world_from_model: Pose,
    pub view_count: usize,
    /// GPU bytes held (vertices, views, blends, images).
    pub bytes: u64,
}

fn buffer(
    device: &wgpu::Device,
    label: &str,
    bytes: &[u8],
    usage: wgpu::BufferUsages,
) -> wgpu::Buffer {
    use wgpu::util::DeviceExt;
    device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(label),
        contents: bytes,
        usage,
    })
}

/// The view's camera and pose for the shader.
fn eo_view_uniform(
    prepared: &PreparedVdtm,
    world_from_eo: &Pose,
    world_from_model: &Pose,
) -> EoViewUniform {
    eo_view_uniform_of(&prepared.camera, world_from_eo, world_from_model)
}

/// An acquisition view's camera `c`, taken at `world_from_eo`, for a shader whose
/// positions are relative to `world_from_model` (`EoView` in `eo_camera.wgsl`).
pub(crate) fn eo_view_uniform_of(
    c: &PinholeCamera,
    world_from_eo: &Pose,
    world_from_model: &Pose,
) -> EoViewUniform {
    let eo_from_model = gpu_from_pose_relative(&world_from_eo.inverse(), world_from_model);
    let model_from_eo = gpu_from_pose_relative(&world_from_model.inverse(), world_from_eo);
    let (k, p) = match &c.distortion {
        Distortion::None => ([0.0; 3], [0.0; 2]),
        Distortion::PlumbBob(b) => ([b.k1, b.k2, b.k3], [b.p1, b.p2]),
    };
    EoViewUniform {
        eo_from_model,
        centre_model: model_from_eo.w_axis,
        intrinsics: Vec4::new(c.fx as f32, c.fy as f32, c.cx as f32, c.cy as f32),
        shape: Vec4::new(
            c.skew as f32,
            c.width as f32,
            c.height as f32,
            c.max_radius_squared()
                .filter(|m| m.is_finite() && *m > 0.0)
                .map_or(0.0, |m| m as f32),
        ),
        distortion: Vec4::new(k[0] as f32, k[1] as f32, p[0] as f32, p[1] as f32),
        distortion_k3: Vec4::new(k[2] as f32, 0.0, 0.0, 0.0),
    }
}

/// A blend for the shader: at most three views, weights clamped to [0, 1].
pub fn polygon_blend(blend: Option<&texel_vdtm::Blend>) -> PolygonBlend {
    let mut views = [0u32; 4];
    let mut weights = [0.0f32; 4];
    let mut n = 0;
    if let Some(b) = blend {
        for (i, (view, weight)) in b.iter().take(3).enumerate() {
            views[i] = view;
            weights[i] = (weight as f32).clamp(0.0, 1.0);
            n = i + 1;
        }
    }
    views[3] = n as u32;
    PolygonBlend {
        views: UVec4::from_array(views),
        weights: Vec4::from_array(weights),
    }
}

impl GpuVdtm {
    pub fn upload(
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        prepared: &PreparedVdtm,
    ) -> Result<Self, GpuError> {
        let model = &prepared.model;
        let mesh = &model.mesh;
        // Draw order: holes, then single views, then view maps (§8: holes first).
        let rank = |t: &Texturing| match t {
            Texturing::Hole { .. } => 0u8,
            Texturing::Single(_) => 1,
            Texturing::Mapped(_) => 2,
        };
        let mut slots: Vec<u32> = (0..model.texturing.len())
            .filter_map(|t| u32::try_from(t).ok())
            .collect();
        slots.sort_by_key(|&t| model.texturing.get(t as usize).map_or(0, rank));
        let count_rank = |r: u8| {
            slots
                .iter()
                .filter(|&&t| model.texturing.get(t as usize).map(rank) == Some(r))
                .count()
        };
        let holes = count_rank(0);
        let mapped_from = holes + count_rank(1);

        let mut vertices = Vec::with_capacity(slots.len() * 3);
        let mut blends = Vec::with_capacity(slots.len());
        for (slot, &t) in slots.iter().enumerate() {
            let tri = mesh.triangles.get(t as usize).copied().unwrap_or([0; 3]);
            let (corners, blend) = match model.texturing.get(t as usize) {
                Some(Texturing::Hole { corners }) => (*corners, polygon_blend(None)),
                Some(Texturing::Single(view)) => (
                    [[0.5; 3]; 3],
                    polygon_blend(Some(&texel_vdtm::Blend::single(*view))),
                ),
                _ => ([[0.5; 3]; 3], polygon_blend(None)),
            };
            for (corner, &v) in tri.iter().enumerate() {
                let position = mesh.positions.get(v as usize).copied().unwrap_or([0.0; 3]);
                let c = corners[corner].map(|x| (x.clamp(0.0, 1.0) * 255.0).round() as u8);
                vertices.push(VdtmVertex {
                    position,
                    colour: [c[0], c[1], c[2], 255],
                    polygon: slot as u32,
                });
            }
            blends.push(blend);
        }
        if vertices.is_empty() {
            // wgpu rejects empty buffers; one degenerate triangle draws nothing.
            vertices = vec![VdtmVertex::zeroed(); 3];
            blends.push(PolygonBlend::zeroed());
        }

        let world_from_model = Pose::from_parts(
            Translation3::from(prepared.origin().coords),
            nalgebra::UnitQuaternion::identity(),
        );
        let mut views: Vec<EoViewUniform> = prepared
            .views
            .iter()
            .map(|v| eo_view_uniform(prepared, &v.world_from_eo, &world_from_model))
            .collect();
        let view_count = views.len();
        if views.is_empty() {
            views.push(EoViewUniform::zeroed());
        }

        let images = Self::image_array(device, queue, prepared)?;
        let vertex_bytes: &[u8] = bytemuck::cast_slice(&vertices);
        let view_bytes: &[u8] = bytemuck::cast_slice(&views);
        let blend_bytes: &[u8] = bytemuck::cast_slice(&blends);
        let limit = device.limits().max_storage_buffer_binding_size;
        if blend_bytes.len() as u64 > limit {
            return Err(GpuError::TooLarge {
                what: "the VDTM polygon blends",
                bytes: blend_bytes.len() as u64,
                limit,
            });
        }
        let image_bytes = 4
            * u64::from(prepared.camera.width)
            * u64::from(prepared.camera.height)
            * view_count.max(1) as u64;
        let bytes =
            (vertex_bytes.len() + view_bytes.len() + blend_bytes.len()) as u64 + image_bytes;
        Ok(Self {
            vertices: buffer(
                device,
                "vdtm vertices",
                vertex_bytes,
                wgpu::BufferUsages::VERTEX,
            ),
            views: buffer(
                device,
                "vdtm views",
                view_bytes,
                wgpu::BufferUsages::STORAGE,
            ),
            blends: buffer(
                device,
                "vdtm blends",
                blend_bytes,
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            ),
            images,
            scratch: vec![PolygonBlend::zeroed(); slots.len().saturating_sub(mapped_from)],
            slots,
            holes: holes as u32,
            mapped_from,
            world_from_model,
            view_count,
            bytes,
        })
    }

    /// Every view's image as one layer of an `EO_FORMAT` array (RGB made RGBA).
    fn image_array(
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        prepared: &PreparedVdtm,
    ) -> Result<wgpu::TextureView, GpuError> {
        let limits = device.limits();
        let (width, height) = (prepared.camera.width, prepared.camera.height);
        let layers = u32::try_from(prepared.views.len().max(1)).unwrap_or(u32::MAX);
        if width > limits.max_texture_dimension_2d || height > limits.max_texture_dimension_2d {
            return Err(GpuError::TextureTooLarge {
                id: 0,
                width,
                height,
                limit: limits.max_texture_dimension_2d,
            });
        }
        if layers > limits.max_texture_array_layers {
            return Err(GpuError::TooManyViews {
                views: layers as usize,
                limit: limits.max_texture_array_layers,
            });
        }
        let size = wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: layers,
        };
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("vdtm images"),
            size,
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: EO_FORMAT,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        for (layer, view) in prepared.views.iter().enumerate() {
            let image = &view.image;
            let expected = 3 * width as usize * height as usize;
            if image.width != width || image.height != height || image.rgb.len() != expected {
                return Err(GpuError::BadTexture {
                    id: view.scan,
                    width: image.width,
                    height: image.height,
                    bytes: image.rgb.len(),
                });
            }
            let rgba = rgba_of_rgb(&image.rgb);
            queue.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture: &texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d {
                        x: 0,
                        y: 0,
                        z: layer as u32,
                    },
                    aspect: wgpu::TextureAspect::All,
                },
                &rgba,
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(4 * width),
                    rows_per_image: Some(height),
                },
                wgpu::Extent3d {
                    width,
                    height,
                    depth_or_array_layers: 1,
                },
            );
        }
        Ok(texture.create_view(&wgpu::TextureViewDescriptor {
            dimension: Some(wgpu::TextureViewDimension::D2Array),
            ..Default::default()
        }))
    }

    /// Polygons drawn (holes included).
    pub fn polygons(&self) -> usize {
        self.slots.len()
    }

    /// Vertices in the buffer (3 per draw slot, at least one triangle).
    pub(crate) fn vertex_count(&self) -> u32 {
        u32::try_from(self.slots.len().max(1) * 3).unwrap_or(u32::MAX)
    }

    /// §8 for this frame: each view-mapped polygon's views and weights for an eye at
    /// `eye` (world), written to the blend buffer.
    pub fn update_blends(
        &mut self,
        queue: &wgpu::Queue,
        prepared: &PreparedVdtm,
        eye: &Point3<f64>,
    ) {
        let slots = self.slots.get(self.mapped_from..).unwrap_or(&[]);
        for (out, &t) in self.scratch.iter_mut().zip(slots) {
            *out = polygon_blend(prepared.model.blend(t as usize, eye).as_ref());
        }
        if !self.scratch.is_empty() {
            queue.write_buffer(
                &self.blends,
                self.mapped_from as u64 * BLEND_BYTES,
                bytemuck::cast_slice(&self.scratch),
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{Point3, Vector2, Vector3};
    use texel::camera::PinholeCamera;
    use texel::distortion::PlumbBob;

    use super::*;

    /// `project_eo` of `vdtm.wgsl`, step for step in f32.
    fn project_f32(v: &EoViewUniform, p_model: [f32; 3]) -> Option<[f32; 2]> {
        let q = v
            .eo_from_model
            .transform_point3(glam::Vec3::from_array(p_model));
        if q.z <= 1e-6 {
            return None;
        }
        let (x, y) = (q.x / q.z, q.y / q.z);
        let r2 = x * x + y * y;
        if v.shape.w > 0.0 && r2 >= v.shape.w {
            return None;
        }
        let d = v.distortion;
        let radial = 1.0 + r2 * (d.x + r2 * (d.y + r2 * v.distortion_k3.x));
        let xd = x * radial + 2.0 * d.z * x * y + d.w * (r2 + 2.0 * x * x);
        let yd = y * radial + d.z * (r2 + 2.0 * y * y) + 2.0 * d.w * x * y;
        let k = v.intrinsics;
        Some([k.x * xd + v.shape.x * yd + k.z, k.y * yd + k.w])
    }

    fn camera() -> PinholeCamera {
        PinholeCamera {
            width: 640,
            height: 480,
            fx: 520.0,
            fy: 518.0,
            cx: 322.5,
            cy: 236.8,
            skew: 0.0,
            distortion: Distortion::PlumbBob(PlumbBob {
                k1: -0.25,
                k2: 0.08,
                p1: 0.001,
                p2: -0.0008,
                k3: -0.01,
            }),
        }
    }

    /// Per fragment in f32, relative to a model origin 2 km out and 30 m from the
    /// view, the distortion lands within a hundredth of a pixel of the f64 camera
    /// model over the whole image and 1 to 40 m of depth. Per vertex (the pixel
    /// interpolated across a polygon, perspective-correctly) would err by the
    /// distortion's curvature across the polygon: measured here for a polygon of the
    /// merged surface's size (5 cm at 1 m) and for one ten times larger.
    #[test]
    fn per_fragment_distortion_matches_the_camera_model() {
        let cam = camera();
        let origin = Point3::new(1000.0, 2000.0, 50.0);
        let world_from_model = Pose::from_parts(
            Translation3::from(origin.coords),
            nalgebra::UnitQuaternion::identity(),
        );
        let world_from_eo = Pose::from_parts(
            Translation3::new(1020.0, 1978.0, 52.0),
            nalgebra::UnitQuaternion::from_euler_angles(0.3, -0.7, 1.9),
        );
        let v = EoViewUniform {
            eo_from_model: gpu_from_pose_relative(&world_from_eo.inverse(), &world_from_model),
            centre_model: Vec4::ZERO,
            intrinsics: Vec4::new(cam.fx as f32, cam.fy as f32, cam.cx as f32, cam.cy as f32),
            shape: Vec4::new(0.0, 640.0, 480.0, 0.0),
            distortion: Vec4::new(-0.25, 0.08, 0.001, -0.0008),
            distortion_k3: Vec4::new(-0.01, 0.0, 0.0, 0.0),
        };
        let (mut worst, mut per_vertex_small, mut per_vertex_large) = (0.0f64, 0.0f64, 0.0f64);
        for py in (0..480).step_by(24) {
            for px in (0..640).step_by(32) {
                let pixel = Vector2::new(f64::from(px), f64::from(py));
                let ray = cam.unproject_ray(pixel).unwrap();
                for depth in [1.0, 4.0, 15.0, 40.0] {
                    let eo = ray * (depth / ray.z);
                    let world = world_from_eo * Point3::from(eo);
                    let local = (world - origin).map(|c| c as f32);
                    let got = project_f32(&v, [local.x, local.y, local.z]).unwrap();
                    let e = ((f64::from(got[0]) - pixel.x).powi(2)
                        + (f64::from(got[1]) - pixel.y).powi(2))
                    .sqrt();
                    worst = worst.max(e);
                }
                // Per vertex: the centroid of a polygon facing the camera at 1 m,
                // its pixel taken as the mean of its corners' (what interpolation
                // gives at the centroid of a fronto-parallel polygon).
                for (side_m, out) in [(0.05, &mut per_vertex_small), (0.5, &mut per_vertex_large)] {
                    let n = Vector3::new(ray.x / ray.z, ray.y / ray.z, 1.0);
                    let corners = [
                        n + Vector3::new(side_m, 0.0, 0.0),
                        n + Vector3::new(-side_m / 2.0, side_m * 0.866, 0.0),
                        n + Vector3::new(-side_m / 2.0, -side_m * 0.866, 0.0),
                    ];
                    let Ok(pixels) = corners
                        .iter()
                        .map(|c| cam.project(c))
                        .collect::<Result<Vec<_>, _>>()
                    else {
                        continue;
                    };
                    let mean = (pixels[0] + pixels[1] + pixels[2]) / 3.0;
                    let exact = cam.project(&n).unwrap();
                    *out = out.max((mean - exact).norm());
                }
            }
        }
        println!(
            "per fragment (f32): {worst:.4} px; per vertex: {per_vertex_small:.3} px for 5 cm polygons at 1 m, {per_vertex_large:.2} px for 50 cm ones"
        );
        assert!(worst < 0.02, "{worst}");
        assert!(per_vertex_large > worst, "{per_vertex_large} vs {worst}");
    }

    #[test]
    fn blends_keep_three_views_and_weights_in_range() {
        let none = polygon_blend(None);
        assert_eq!(none.views.w, 0);
        let one = polygon_blend(Some(&texel_vdtm::Blend::single(7)));
        assert_eq!((one.views.x, one.views.w, one.weights.x), (7, 1, 1.0));
    }
}
