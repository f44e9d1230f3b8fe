//! A served scan as Foxglove draws it: its `ScanAdded` frame (as the hub holds it)
//! turned into a `foxglove.SceneEntity` in `world` holding one model primitive, the
//! scan's textured mesh as a binary glTF (`texel::export::scan_glb`) placed by the
//! primitive's pose, `world_from_scan`.
//!
//! The mesh stays in the scan's own frame (f32 relative to the scan's origin) and the
//! f64 pose travels in the primitive, so a model far from the origin draws as well as
//! one at it. The texture goes into the glTF as it travelled (the stream's JPEG or
//! PNG, embedded unchanged); only a raw RGB texture is compressed (to PNG) here.
//! Foxglove turns every glTF from glTF's +Y up to its +Z up (a quarter turn about x);
//! the glTF's root node holds the opposite turn, so the mesh reaches Foxglove in the
//! scan's own coordinates.

use std::f64::consts::FRAC_1_SQRT_2;
use std::sync::Arc;

use foxglove::messages::{
    KeyValuePair, ModelPrimitive, Pose as FoxglovePose, Quaternion, SceneEntity,
    SceneEntityDeletion, Vector3,
};
use nalgebra::{Translation3, UnitQuaternion};
use texel::capture::{frame_ids, timestamp_from_nanos};
use texel::export::{GltfTexture, scan_glb};
use texel::model::ScanId;
use texel::pose::pose_to_parts;
use texel::wire::{Limits, Message, TextureFormat, decode_frame};
use texel::{EoFrame, Pose};
use thiserror::Error;

/// The media type of a binary glTF.
pub const GLB_MEDIA_TYPE: &str = "model/gltf-binary";

#[derive(Debug, Error)]
pub enum ModelError {
    #[error("scan {id}: its frame does not decode: {message}")]
    Frame { id: ScanId, message: String },
    #[error("scan {id}: {source}")]
    Gltf {
        id: ScanId,
        source: texel::export::ExportError,
    },
}

/// A scan's model, ready to be placed.
pub struct ScanModel {
    pub id: ScanId,
    pub timestamp_ns: u64,
    pub glb: bytes::Bytes,
}

/// The rotation Foxglove's Y-up to Z-up turn undoes: -90 degrees about x.
fn z_up_root() -> Pose {
    Pose::from_parts(
        Translation3::identity(),
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            FRAC_1_SQRT_2,
            -FRAC_1_SQRT_2,
            0.0,
            0.0,
        )),
    )
}

/// The scan a `ScanAdded` frame carries, as a GLB (blocking work: call from a
/// blocking thread).
pub fn scan_model(id: ScanId, frame: &[u8]) -> Result<ScanModel, ModelError> {
    let wire = match decode_frame(frame, &Limits::FROM_SERVER) {
        Ok(Some((Message::ScanAdded(wire), _))) => wire,
        Ok(_) => {
            return Err(ModelError::Frame {
                id,
                message: "not a whole ScanAdded frame".into(),
            });
        }
        Err(e) => {
            return Err(ModelError::Frame {
                id,
                message: e.to_string(),
            });
        }
    };
    let mut wire = *wire;
    let format = wire.texture.format;
    let (width, height) = (wire.texture.width, wire.texture.height);
    let image = std::mem::take(&mut wire.texture.data);
    let (_, mut scan, _) = wire.into_geometry();
    let encoded;
    let texture = match format {
        TextureFormat::Jpeg | TextureFormat::Png => {
            encoded = image;
            GltfTexture::Encoded {
                mime_type: if format == TextureFormat::Jpeg {
                    "image/jpeg"
                } else {
                    "image/png"
                },
                data: &encoded,
            }
        }
        TextureFormat::Rgb8 => {
            scan.texture = Arc::new(EoFrame {
                width,
                height,
                rgb: image,
                timestamp_ns: scan.timestamp_ns,
                exposure: None,
            });
            GltfTexture::Png
        }
    };
    let glb = scan_glb(&scan, texture, Some(z_up_root()))
        .map_err(|source| ModelError::Gltf { id, source })?;
    Ok(ScanModel {
        id,
        timestamp_ns: scan.timestamp_ns,
        glb: glb.into(),
    })
}

/// The entity id of scan `id` on `/texel/scan`.
pub fn entity_id(id: ScanId) -> String {
    id.to_string()
}

fn foxglove_pose(pose: &Pose) -> FoxglovePose {
    let (t, q) = pose_to_parts(pose);
    FoxglovePose {
        position: Some(Vector3 {
            x: t[0],
            y: t[1],
            z: t[2],
        }),
        orientation: Some(Quaternion {
            x: q[0],
            y: q[1],
            z: q[2],
            w: q[3],
        }),
    }
}

/// The scan's entity in `world`, at `world_from_scan`.
pub fn entity(model: &ScanModel, world_from_scan: &Pose) -> SceneEntity {
    SceneEntity {
        timestamp: Some(timestamp_from_nanos(model.timestamp_ns)),
        frame_id: frame_ids::WORLD.to_string(),
        id: entity_id(model.id),
        metadata: vec![KeyValuePair {
            key: "timestamp_ns".into(),
            value: model.timestamp_ns.to_string(),
        }],
        models: vec![ModelPrimitive {
            pose: Some(foxglove_pose(world_from_scan)),
            // Foxglove scales by this: zero would hide the model.
            scale: Some(Vector3 {
                x: 1.0,
                y: 1.0,
                z: 1.0,
            }),
            color: None,
            override_color: false,
            url: String::new(),
            media_type: GLB_MEDIA_TYPE.into(),
            data: model.glb.clone(),
        }],
        ..SceneEntity::default()
    }
}

/// The deletion of scan `id`'s entity (it left the served model).
pub fn deletion(id: ScanId, timestamp_ns: u64) -> SceneEntityDeletion {
    SceneEntityDeletion {
        timestamp: Some(timestamp_from_nanos(timestamp_ns)),
        r#type: foxglove::messages::scene_entity_deletion::Type::MatchingId as i32,
        id: entity_id(id),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_root_turn_undoes_foxgloves_y_up_turn() {
        // Foxglove turns a glTF scene +90 degrees about x.
        let foxglove = UnitQuaternion::from_axis_angle(
            &nalgebra::Vector3::x_axis(),
            0.5 * std::f64::consts::PI,
        );
        let p = nalgebra::Point3::new(0.3, -1.2, 4.5);
        let shown = foxglove * z_up_root().transform_point(&p);
        assert!((shown - p).norm() < 1e-12);
    }
}
