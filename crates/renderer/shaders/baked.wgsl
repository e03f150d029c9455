// Stage: baked-field lookup (lp3d.render.baked.baked_lookup; docs/baked.md). In place of the
// triplane fetch and the decoder, the raw density and RGB at a point are interpolated
// (trilinearly) from values the decoder produced once at the points of a finer grid, stored
// only in the occupancy cells that may hold density (and their neighbours a sample interval
// away): the decoder is skipped. The RGB is stored premultiplied by each point's colour weight,
// so that at a surface the corners in empty space (whose decoded colour is anything) do not
// tint it.
// needs: params, baked, halves_to_f32, plane_coords
// provides: BAKED, BAKED_EMPTY, BAKED_EMPTY_RAW, BAKED_COLOUR_FLOOR, BAKED_COLOUR_RAMP,
// provides: baked_colour_weight, baked_point, baked_sample

// true: render_rays looks samples up in the baked field (a pipeline of its own).
override BAKED: bool = false;

// baked_index of a cell without a brick.
const BAKED_EMPTY: u32 = 0xffffffffu;
// The raw density of a point in a cell without a brick: no decoded interval reaches such a
// cell, and its true raw density is below the occupancy threshold; softplus(-60 - 1) * delta
// is ~1e-28.
const BAKED_EMPTY_RAW: f32 = -60.0;
// Every point's colour weight is at least this: where all eight corners are nearly transparent
// the colour is their plain mean, not a ratio of float16 roundings; and next to a surface the
// colour turns slowly enough within a sub-cell that float32's rounding of a sample's position
// barely moves it (lp3d.render.baked.COLOUR_FLOOR says more).
const BAKED_COLOUR_FLOOR: f32 = 0.03;
// Above the floor the weight climbs linearly with the raw density, from 0 to 1 at this one (a
// ramp, not the opacity: no exp or log for each of a sample's eight corners).
const BAKED_COLOUR_RAMP: f32 = 50.0;

// The colour weight of a point of raw density `sigma_raw`.
fn baked_colour_weight(sigma_raw: f32) -> f32 {
    return BAKED_COLOUR_FLOOR + clamp(sigma_raw / BAKED_COLOUR_RAMP, 0.0, 1.0);
}

// Point (a, b, c) of `brick`, each in 0..=k: (sigma_raw, w r, w g, w b), w its colour weight.
fn baked_point(brick: u32, a: u32, b: u32, c: u32, k1: u32) -> vec4<f32> {
    let w = params.baked_values_offset + 2u * (((brick * k1 + a) * k1 + b) * k1 + c);
    return vec4<f32>(halves_to_f32(baked[w]), halves_to_f32(baked[w + 1u]));
}

// The baked raw density at world point `pos` (returned) and its RGB into dst[0].xyz (w = 0).
// Cells are the baked field's (G per axis over plane coordinates [-1, 1], the edge cells clamped
// so they stand for everything beyond); inside a cell, k intervals per axis.
fn baked_sample(pos: vec3<f32>, dst: ptr<function, array<vec4<f32>, 8>>) -> f32 {
    let g = params.baked_cells;
    let k = params.baked_subdivisions;
    let gf = f32(g);
    let s = (plane_coords(pos) + 1.0) * (0.5 * gf);
    let cell_f = clamp(floor(s), vec3<f32>(0.0), vec3<f32>(gf - 1.0));
    let cell = vec3<u32>(cell_f);
    let brick = baked[(cell.x * g + cell.y) * g + cell.z];
    if (brick == BAKED_EMPTY) {
        (*dst)[0] = vec4<f32>(0.0);
        return BAKED_EMPTY_RAW;
    }
    let kf = f32(k);
    let local = clamp((s - cell_f) * kf, vec3<f32>(0.0), vec3<f32>(kf));
    let i0_f = min(floor(local), vec3<f32>(kf - 1.0));
    let f = local - i0_f;
    let i0 = vec3<u32>(i0_f);
    let k1 = k + 1u;
    var acc = vec4<f32>(0.0);
    var weight = 0.0;
    // The 8 corners as one loop (corner c: + (c & 1, c >> 1 & 1, c >> 2)), not eight copies:
    // lavapipe inlines every call.
    for (var c = 0u; c < 8u; c++) {
        let d = vec3<u32>(c & 1u, (c >> 1u) & 1u, c >> 2u);
        let w3 = select(1.0 - f, f, d == vec3<u32>(1u));
        let t = w3.x * w3.y * w3.z;
        let point = baked_point(brick, i0.x + d.x, i0.y + d.y, i0.z + d.z, k1);
        acc += t * point;
        weight += t * baked_colour_weight(point.x);
    }
    (*dst)[0] = vec4<f32>(acc.yzw / weight, 0.0); // un-premultiplied
    return acc.x;
}
