// eo_camera.wgsl: an acquisition view's calibrated EO camera (pose, intrinsics,
// plumb_bob distortion) and the projection through it, shared by the modes that
// texture from the acquisition images (vdtm.wgsl, points.wgsl).

// One acquisition view: where its EO camera was and the calibrated model it took
// its image with.
struct EoView {
    eo_from_model: mat4x4<f32>,
    // xyz: the centre of projection in the model frame
    centre_model: vec4<f32>,
    // fx, fy, cx, cy (pixel centres at integers)
    intrinsics: vec4<f32>,
    // skew, width, height, the distortion's largest normalised radius squared (0:
    // unbounded)
    shape: vec4<f32>,
    // k1, k2, p1, p2
    distortion: vec4<f32>,
    // x: k3
    distortion_k3: vec4<f32>,
}

// A model-frame point's pixel in an acquisition view (distortion included, pixel
// centres at integers) and its distance from the view's centre; z is 0 when the point
// is behind the camera or outside the distortion model's domain.
fn project_eo(view: EoView, p_model: vec3<f32>) -> vec4<f32> {
    let q = (view.eo_from_model * vec4<f32>(p_model, 1.0)).xyz;
    if q.z <= 1e-6 {
        return vec4<f32>(0.0);
    }
    let x = q.x / q.z;
    let y = q.y / q.z;
    let r2 = x * x + y * y;
    if view.shape.w > 0.0 && r2 >= view.shape.w {
        return vec4<f32>(0.0);
    }
    let d = view.distortion;
    let radial = 1.0 + r2 * (d.x + r2 * (d.y + r2 * view.distortion_k3.x));
    let xd = x * radial + 2.0 * d.z * x * y + d.w * (r2 + 2.0 * x * x);
    let yd = y * radial + d.z * (r2 + 2.0 * y * y) + 2.0 * d.w * x * y;
    let k = view.intrinsics;
    let px = k.x * xd + view.shape.x * yd + k.z;
    let py = k.y * yd + k.w;
    return vec4<f32>(px, py, 1.0, length(q));
}

