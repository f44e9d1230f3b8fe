// Shows a frame rendered offscreen (display values, RGBA8) in the window's target:
// the interactive frame upscaled bilinearly, the full-quality frame pixel for pixel.

// Declared for `common.wgsl`'s helpers; not bound by these entry points.
@group(0) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(1) var picture: texture_2d<f32>;
@group(0) @binding(2) var smooth_sampler: sampler;

// The target stores linear values (an sRGB format): decode the display values first.
override SRGB_TARGET: bool = false;

struct PresentOut {
    @builtin(position) clip: vec4<f32>,
    // 0..1 over the target, y down (texture coordinates).
    @location(0) uv: vec2<f32>,
}

@vertex
fn vs_present(@builtin(vertex_index) i: u32) -> PresentOut {
    let x = f32((i << 1u) & 2u) * 2.0 - 1.0;
    let y = f32(i & 2u) * 2.0 - 1.0;
    return PresentOut(vec4<f32>(x, y, 0.0, 1.0), vec2<f32>(0.5 * (x + 1.0), 0.5 * (1.0 - y)));
}

fn present(c: vec4<f32>) -> vec4<f32> {
    if SRGB_TARGET {
        return vec4<f32>(srgb_to_linear(c.rgb), 1.0);
    }
    return vec4<f32>(c.rgb, 1.0);
}

// A smaller picture stretched over the target.
@fragment
fn fs_upscale(in: PresentOut) -> @location(0) vec4<f32> {
    return present(textureSampleLevel(picture, smooth_sampler, in.uv, 0.0));
}

// A picture of the target's size, copied pixel for pixel.
@fragment
fn fs_exact(in: PresentOut) -> @location(0) vec4<f32> {
    return present(textureLoad(picture, vec2<i32>(in.clip.xy), 0));
}
