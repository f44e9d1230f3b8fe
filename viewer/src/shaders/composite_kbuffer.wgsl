// composite_kbuffer.wgsl: shades each pixel from its k-buffer entries (already
// valid, range compliant and ranked) into the given target.

@group(0) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(1) var<storage, read> kbuf: array<Ranked>;

@fragment
fn fs_composite(in: FullscreenOut) -> @location(0) vec4<f32> {
    let xy = vec2<u32>(in.clip.xy);
    let k = clamp(frame.counts.y, 1u, MAX_K);
    let base = (xy.y * frame.counts.w + xy.x) * k;
    var top: array<Ranked, MAX_K>;
    var count = 0u;
    for (var i = 0u; i < k; i = i + 1u) {
        let e = kbuf[base + i];
        if e.reliability > 0.0 {
            top[count] = e;
            count = count + 1u;
        }
    }
    return to_target(shade(&top, count));
}
