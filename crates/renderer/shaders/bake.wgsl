// Stage: the bake (lp3d.render.baked.bake_reference; docs/baked.md): the bake_field entry point,
// which decodes the triplane once at every point of every brick of the baked field.
// needs: params, bake_cells, bake_out, sample_triplane, decode, halves_to_f32, baked_colour_weight
// provides: f32_to_half, bake_field

// float32 -> float16 bits, rounded to nearest even (numpy's float16 conversion); magnitudes
// above the largest float16 (65504) are clamped to it. By hand rather than pack2x16float, which
// naga gates behind a capability not every backend has (as unpack2x16float, triplane.wgsl).
fn f32_to_half(x: f32) -> u32 {
    let sign = (bitcast<u32>(x) >> 16u) & 0x8000u;
    let a = min(abs(x), 65504.0);
    if (a < 6.1035156e-5) {
        // Subnormal (or zero): a multiple of 2^-24; round() rounds half to even.
        return sign | u32(round(a * 16777216.0));
    }
    let bits = bitcast<u32>(a);
    var h = (((bits >> 23u) - 112u) << 10u) | ((bits >> 13u) & 0x3ffu);
    let rest = bits & 0x1fffu;
    if (rest > 0x1000u || (rest == 0x1000u && (h & 1u) == 1u)) {
        h += 1u; // a carry into the exponent is the right rounding too
    }
    return sign | h;
}

// One invocation per point: point p of brick i = id / (k + 1)^3, at grid index
// cell * k + (a, b, c) of the G k grid over plane coordinates [-1, 1]. A bake runs as several
// dispatches (so that a viewer keeps drawing meanwhile); params.camera_offset is the first point
// of this one.
@compute @workgroup_size(64)
fn bake_field(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let g = params.baked_cells;
    let k = params.baked_subdivisions;
    let k1 = k + 1u;
    let per_brick = k1 * k1 * k1;
    let id = params.camera_offset + gid.x + gid.y * groups.x * 64u;
    let brick = id / per_brick;
    if (brick >= arrayLength(&bake_cells)) {
        return;
    }
    let p = id % per_brick;
    let cell = bake_cells[brick];
    let ijk = vec3<u32>(cell / (g * g), (cell / g) % g, cell % g) * k + vec3<u32>(p / (k1 * k1), (p / k1) % k1, p % k1);
    let q = vec3<f32>(ijk) * (2.0 / f32(g * k)) - 1.0;
    var feat = array<vec4<f32>, 8>();
    var rgb = array<vec4<f32>, 8>();
    sample_triplane(q * (0.5 * params.box_warp), &feat);
    let sigma_raw = f32_to_half(decode(3u, &feat, &rgb));
    // The weight of the raw density as stored, which is what the lookup recomputes it from.
    let weight = baked_colour_weight(halves_to_f32(sigma_raw).x);
    let w = params.baked_values_offset + 2u * id;
    bake_out[w] = sigma_raw | (f32_to_half(rgb[0].x * weight) << 16u);
    bake_out[w + 1u] = f32_to_half(rgb[0].y * weight) | (f32_to_half(rgb[0].z * weight) << 16u);
}
