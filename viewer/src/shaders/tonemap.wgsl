// tonemap.wgsl: linear radiance (a float texture) to display values, mirroring
// `tonemap.rs` step for step. Auto-exposure: `cs_partial` sums ln(eps + L) over 16 x 16
// tiles, `cs_final` sums the tiles and writes the log-average luminance (Lechelek et
// al. 2019, eq. 9); `fs_tonemap` scales by key / L_a (eq. 10), compresses (eq. 11, or
// the filmic curve, or clipping), applies exposure and gamma (eq. 12). Pixels of alpha 0
// hold no surface (a rendered view's background): they show the frame's background and
// do not count towards the log-average.

struct ToneMap {
    // x: operator (0 Reinhard, 1 filmic, 2 clip), y: key, z: exposure (a linear
    // factor, 2^ev), w: 1 / gamma
    params: vec4<f32>,
    // x: 1 for auto-exposure, y: the fixed adaptation level, z: epsilon of eq. 9
    adapt: vec4<f32>,
    // x, y: radiance image size; z: tile count of `cs_partial`
    size: vec4<u32>,
}

const LUMINANCE: vec3<f32> = vec3<f32>(0.2126, 0.7152, 0.0722);
const TILE: u32 = 16u;
const FINAL_THREADS: u32 = 256u;

@group(0) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(1) var<uniform> tone: ToneMap;
@group(0) @binding(2) var radiance: texture_2d<f32>;
// Per tile: (sum of ln(eps + L), pixel count). Written by cs_partial, read by cs_final.
@group(0) @binding(3) var<storage, read_write> partials: array<vec2<f32>>;
// The adaptation level L_a: written by cs_final ...
@group(0) @binding(4) var<storage, read_write> adaptation_out: array<f32>;
// ... and read by fs_tonemap (the same buffer, bound read-only there).
@group(0) @binding(5) var<storage, read> adaptation_in: array<f32>;

var<workgroup> shared_sum: array<vec2<f32>, 256>;

fn finite_or_zero(v: vec3<f32>) -> vec3<f32> {
    // NaN fails both comparisons; infinities fail the second.
    let ok = (v >= vec3<f32>(0.0)) & (v < vec3<f32>(3.0e38));
    return select(vec3<f32>(0.0), v, ok);
}

fn reduce_shared(local: u32) {
    var stride = 128u;
    loop {
        if stride == 0u {
            break;
        }
        if local < stride {
            shared_sum[local] = shared_sum[local] + shared_sum[local + stride];
        }
        workgroupBarrier();
        stride = stride / 2u;
    }
}

@compute @workgroup_size(16, 16)
fn cs_partial(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    var value = vec2<f32>(0.0, 0.0);
    if gid.x < tone.size.x && gid.y < tone.size.y {
        let texel = textureLoad(radiance, vec2<i32>(gid.xy), 0);
        // Alpha 0: no surface there (a rendered view's background); not counted.
        if texel.a > 0.0 {
            let l = max(dot(LUMINANCE, finite_or_zero(texel.rgb)), 0.0);
            value = vec2<f32>(log(tone.adapt.z + l), 1.0);
        }
    }
    shared_sum[local] = value;
    workgroupBarrier();
    reduce_shared(local);
    if local == 0u {
        partials[wg.y * groups.x + wg.x] = shared_sum[0];
    }
}

@compute @workgroup_size(256)
fn cs_final(@builtin(local_invocation_index) local: u32) {
    var sum = vec2<f32>(0.0, 0.0);
    var i = local;
    loop {
        if i >= tone.size.z {
            break;
        }
        sum = sum + partials[i];
        i = i + FINAL_THREADS;
    }
    shared_sum[local] = sum;
    workgroupBarrier();
    reduce_shared(local);
    if local == 0u {
        let total = shared_sum[0];
        // An empty image adapts to 1.
        var l_a = 1.0;
        if total.y > 0.0 {
            l_a = exp(total.x / total.y);
        }
        adaptation_out[0] = max(l_a, 1.0e-30);
    }
}

fn aces(x: vec3<f32>) -> vec3<f32> {
    return (x * (2.51 * x + vec3<f32>(0.03))) / (x * (2.43 * x + vec3<f32>(0.59)) + vec3<f32>(0.14));
}

fn tone_map(c_in: vec3<f32>, l_a: f32) -> vec3<f32> {
    let c = finite_or_zero(c_in);
    let scale = tone.params.y / max(l_a, 1.0e-30);
    let exposure = tone.params.z;
    let op = u32(tone.params.x + 0.5);
    var display: vec3<f32>;
    if op == 0u {
        // L_d / L = scale / (1 + L_s): the colour scaled without dividing by L.
        let ls = scale * max(dot(LUMINANCE, c), 0.0);
        display = c * (scale / (1.0 + ls) * exposure);
    } else if op == 1u {
        display = aces(c * (scale * exposure));
    } else {
        display = c * (scale * exposure);
    }
    let clipped = min(finite_or_zero(display), vec3<f32>(1.0));
    return pow(clipped, vec3<f32>(tone.params.w));
}

@fragment
fn fs_tonemap(in: FullscreenOut) -> @location(0) vec4<f32> {
    let pixel = vec2<i32>(in.clip.xy);
    var l_a = tone.adapt.y;
    if tone.adapt.x > 0.5 {
        l_a = adaptation_in[0];
    }
    let texel = textureLoad(radiance, pixel, 0);
    if !(texel.a > 0.0) {
        return to_target(frame.background.rgb);
    }
    return to_target(tone_map(texel.rgb, l_a));
}
