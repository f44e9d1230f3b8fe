// points_fill.wgsl: pull-push (Marroquim et al. 2007, as Lechelek et al. 2019 §4 use
// it) of the front and back images that points.wgsl's pass 2 scattered, mirrored by
// `points/pull_push.rs`. Every level of the pyramid lives in one buffer, a pixel as
// (front value, front weight, back value, back weight). `cs_load` fills level 0,
// `cs_pull` averages each 2 x 2 block of valid pixels into the next level (weights
// summed and capped at 1, never a 0/0), `cs_push` fills each invalid pixel from the
// level above, and `cs_resolve` keeps the front depth, else the back one, where pass 1
// drew (passes 4-5), 0 elsewhere.

struct LevelPair {
    // offset in the buffer, width, height of the finer level
    fine: vec4<u32>,
    // the same of the coarser level
    coarse: vec4<u32>,
}

// The common part's functions name the frame uniform; no entry point here uses it.
@group(1) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(0) var<storage, read_write> levels: array<vec4<f32>>;
@group(0) @binding(1) var<uniform> pair: LevelPair;
// Depth maps: f32 bits in r32uint, 0 where none.
@group(0) @binding(2) var front_z: texture_2d<u32>;
@group(0) @binding(3) var back_z: texture_2d<u32>;
@group(0) @binding(4) var drawn_z: texture_2d<u32>;
@group(0) @binding(5) var resolved: texture_storage_2d<r32uint, write>;

fn fine_index(x: u32, y: u32) -> u32 {
    return pair.fine.x + y * pair.fine.y + x;
}

@compute @workgroup_size(8, 8)
fn cs_load(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= pair.fine.y || id.y >= pair.fine.z {
        return;
    }
    let at = vec2<i32>(id.xy);
    let f = bitcast<f32>(textureLoad(front_z, at, 0).x);
    let b = bitcast<f32>(textureLoad(back_z, at, 0).x);
    levels[fine_index(id.x, id.y)] = vec4<f32>(
        select(0.0, f, f > 0.0), select(0.0, 1.0, f > 0.0),
        select(0.0, b, b > 0.0), select(0.0, 1.0, b > 0.0),
    );
}

@compute @workgroup_size(8, 8)
fn cs_pull(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= pair.coarse.y || id.y >= pair.coarse.z {
        return;
    }
    var sum = vec4<f32>(0.0);
    for (var k = 0u; k < 4u; k++) {
        let fx = 2u * id.x + (k & 1u);
        let fy = 2u * id.y + (k >> 1u);
        if fx < pair.fine.y && fy < pair.fine.z {
            let p = levels[fine_index(fx, fy)];
            sum += vec4<f32>(p.y * p.x, p.y, p.w * p.z, p.w);
        }
    }
    let front = select(0.0, sum.x / sum.y, sum.y > 0.0);
    let back = select(0.0, sum.z / sum.w, sum.w > 0.0);
    levels[pair.coarse.x + id.y * pair.coarse.y + id.x] =
        vec4<f32>(front, min(sum.y, 1.0), back, min(sum.w, 1.0));
}

@compute @workgroup_size(8, 8)
fn cs_push(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= pair.fine.y || id.y >= pair.fine.z {
        return;
    }
    let i = fine_index(id.x, id.y);
    var p = levels[i];
    let parent = levels[pair.coarse.x + (id.y / 2u) * pair.coarse.y + id.x / 2u];
    if p.y <= 0.0 && parent.y > 0.0 {
        p = vec4<f32>(parent.x, 1.0, p.z, p.w);
    }
    if p.w <= 0.0 && parent.w > 0.0 {
        p = vec4<f32>(p.x, p.y, parent.z, 1.0);
    }
    levels[i] = p;
}

@compute @workgroup_size(8, 8)
fn cs_resolve(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= pair.fine.y || id.y >= pair.fine.z {
        return;
    }
    let p = levels[fine_index(id.x, id.y)];
    let drawn = bitcast<f32>(textureLoad(drawn_z, vec2<i32>(id.xy), 0).x) > 0.0;
    let z = select(select(0.0, p.z, p.w > 0.0), p.x, p.y > 0.0);
    textureStore(resolved, vec2<i32>(id.xy), vec4<u32>(bitcast<u32>(select(0.0, z, drawn)), 0u, 0u, 0u));
}
