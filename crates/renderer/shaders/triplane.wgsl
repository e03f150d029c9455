// Stage: triplane fetch (lp3d.render.reference.sample_triplane). EG3D's plane projection (with its
// axis quirk) and grid_sample(bilinear, zeros padding per tap, align_corners=False), averaged
// over planes.
// needs: params, planes, FLAG_HALF_PLANES
// provides: halves_to_f32, add_tap, add_plane, plane_coords, sample_triplane
//
// PLANE_AXES = (x,y), (x,z), (z,x): plane 2 is the transpose of plane 1, not YZ.
// Kept on purpose so EG3D checkpoints render unchanged (docs/triplane-format.md).

// Two float16 (low, high half of `v`) to float32, exactly. By hand rather than
// unpack2x16float, which naga gates behind a capability (SHADER_FLOAT16_IN_FLOAT32) that not
// every backend has; subnormals are scaled from an integer so flush-to-zero cannot drop them.
// Planes are finite (validated), so Inf/NaN encodings never occur.
fn halves_to_f32(v: u32) -> vec2<f32> {
    let h = vec2<u32>(v & 0xffffu, v >> 16u);
    let e = (h >> vec2<u32>(10u)) & vec2<u32>(0x1fu);
    let m = h & vec2<u32>(0x3ffu);
    let normal = bitcast<vec2<f32>>(((e + 112u) << vec2<u32>(23u)) | (m << vec2<u32>(13u)));
    let subnormal = vec2<f32>(m) * 5.9604645e-8; // m * 2^-24
    let mag = select(normal, subnormal, e == vec2<u32>(0u));
    return bitcast<vec2<f32>>(bitcast<vec2<u32>>(mag) | ((h & vec2<u32>(0x8000u)) << vec2<u32>(16u)));
}

fn add_tap(p: u32, x: i32, y: i32, w: f32, feat: ptr<function, array<vec4<f32>, 8>>) {
    let h = i32(params.plane_h);
    let wd = i32(params.plane_w);
    if (x < 0 || y < 0 || x >= wd || y >= h) {
        return; // zeros padding, per tap
    }
    let texel = (p * params.plane_h + u32(y)) * params.plane_w + u32(x);
    if ((params.flags & FLAG_HALF_PLANES) != 0u) {
        // Float16 planes: half the bytes per tap, float32 arithmetic (unpacking is exact).
        let base = texel * 4u;
        for (var q = 0u; q < 4u; q++) {
            let h = planes[base + q];
            (*feat)[2u * q] += w * vec4<f32>(halves_to_f32(h.x), halves_to_f32(h.y));
            (*feat)[2u * q + 1u] += w * vec4<f32>(halves_to_f32(h.z), halves_to_f32(h.w));
        }
    } else {
        let base = texel * 8u;
        for (var q = 0u; q < 8u; q++) {
            (*feat)[q] += w * bitcast<vec4<f32>>(planes[base + q]);
        }
    }
}

// Bilinear taps of grid_sample at normalised (u, v) in [-1, 1] for plane p, added to `feat`.
// The four taps are a loop (corner c: x + (c & 1), y + (c >> 1)), not four copies: lavapipe
// inlines every call, and each copy of add_tap costs compile time (bench/history/RESULTS.md,
// "Kernel compile time").
fn add_plane(p: u32, u: f32, v: f32, feat: ptr<function, array<vec4<f32>, 8>>) {
    let ix = ((u + 1.0) * f32(params.plane_w) - 1.0) * 0.5;
    let iy = ((v + 1.0) * f32(params.plane_h) - 1.0) * 0.5;
    // All four taps outside: nothing to add (also keeps i32 conversions in range).
    if (!(ix > -1.0 && iy > -1.0 && ix < f32(params.plane_w) && iy < f32(params.plane_h))) {
        return;
    }
    let x0 = floor(ix);
    let y0 = floor(iy);
    let fx = ix - x0;
    let fy = iy - y0;
    let xi = i32(x0);
    let yi = i32(y0);
    for (var c = 0u; c < 4u; c++) {
        let dx = c & 1u;
        let dy = c >> 1u;
        let w = select(1.0 - fx, fx, dx == 1u) * select(1.0 - fy, fy, dy == 1u);
        add_tap(p, xi + i32(dx), yi + i32(dy), w, feat);
    }
}

// World point -> plane coordinates ([-1, 1] inside the box).
fn plane_coords(pos: vec3<f32>) -> vec3<f32> {
    return pos * (2.0 / params.box_warp);
}

// Mean of the three plane features at world point `pos`, the 32-channel decoder input, into
// `feat`.
fn sample_triplane(pos: vec3<f32>, feat: ptr<function, array<vec4<f32>, 8>>) {
    let q = plane_coords(pos);
    for (var i = 0u; i < 8u; i++) {
        (*feat)[i] = vec4<f32>(0.0);
    }
    for (var p = 0u; p < 3u; p++) {
        // PLANE_AXES: (x, y), (x, z), (z, x).
        let uv = select(select(q.zx, q.xz, p == 1u), q.xy, p == 0u);
        add_plane(p, uv.x, uv.y, feat);
    }
    for (var i = 0u; i < 8u; i++) {
        (*feat)[i] = (*feat)[i] / 3.0;
    }
}
