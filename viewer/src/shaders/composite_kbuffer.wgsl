// composite_kbuffer.wgsl: shades each pixel from its k-buffer entries (already
// valid, range compliant and ranked) into the given target. In a hybrid frame
// (frame.params.w set: level-of-detail tiles are drawn over the scans), a pixel whose
// neighbours nearly all hold a scan surface nearer than anything it holds is a
// sampling hole of the drawn scans (a dropout, a gap between triangles, through which
// nothing or a farther surface shows): it takes the mean of those neighbours' shades,
// and the tile pass gives way there by the same rule (tile.wgsl), instead of showing
// the coarser tile in a speckle over the scans' surface.

@group(0) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(1) var<storage, read> kbuf: array<Ranked>;
// The pre-pass's nearest valid scan distance and its range sigma per pixel (f32 bit
// patterns; +infinity where no scan drew).
@group(0) @binding(2) var scan_nearest: texture_2d<u32>;

// The valid entries of a pixel's k-buffer list, in rank order; their count.
fn gather(xy: vec2<u32>, top: ptr<function, array<Ranked, MAX_K>>) -> u32 {
    let k = clamp(frame.counts.y, 1u, MAX_K);
    let base = (xy.y * frame.counts.w + xy.x) * k;
    var count = 0u;
    for (var i = 0u; i < k; i = i + 1u) {
        let e = kbuf[base + i];
        if e.reliability > 0.0 {
            (*top)[count] = e;
            count = count + 1u;
        }
    }
    return count;
}

@fragment
fn fs_composite(in: FullscreenOut) -> @location(0) vec4<f32> {
    let xy = vec2<u32>(in.clip.xy);
    var top: array<Ranked, MAX_K>;
    let count = gather(xy, &top);
    if frame.params.w > 0.5 {
        let size = textureDimensions(scan_nearest);
        let here = bitcast<f32>(textureLoad(scan_nearest, xy, 0).x);
        var sum = vec3<f32>(0.0);
        var n = 0u;
        for (var k = 0u; k < 8u; k = k + 1u) {
            let q = neighbour(xy, k, size);
            if q.x < 0 {
                continue;
            }
            let near = textureLoad(scan_nearest, vec2<u32>(q), 0).xy;
            if encloses(here, bitcast<f32>(near.x), bitcast<f32>(near.y)) {
                var entries: array<Ranked, MAX_K>;
                let c = gather(vec2<u32>(q), &entries);
                if c > 0u {
                    sum = sum + shade(&entries, c);
                    n = n + 1u;
                }
            }
        }
        if n >= FILL_MIN_NEIGHBOURS {
            return to_target(sum / f32(n));
        }
    }
    return to_target(shade(&top, count));
}
