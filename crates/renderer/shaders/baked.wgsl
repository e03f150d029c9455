// Stage: baked-field lookup (lp3d.render.baked.baked_lookup; docs/baked.md). In place of the
// triplane fetch and the decoder, the raw density and RGB at a point are interpolated
// (trilinearly) from values the decoder produced once at the points of a finer grid, stored
// only in the occupancy cells that may hold density (and their neighbours a sample interval
// away): the decoder is skipped. The RGB is stored premultiplied by each point's colour weight,
// so that at a surface the corners in empty space (whose decoded colour is anything) do not
// tint it.
// needs: params, baked, baked_fine, halves_to_f32, plane_coords
// provides: BAKED, BAKED_EMPTY, BAKED_FINE, BAKED_EMPTY_RAW, BAKED_COLOUR_FLOOR, BAKED_COLOUR_RAMP,
// provides: baked_colour_weight, baked_word, baked_words, BakedSpot, baked_spot, BakedCorners,
// provides: baked_corners, baked_trilinear, baked_sample

// true: render_rays looks samples up in the baked field (a pipeline of its own).
override BAKED: bool = false;

// baked_index of a cell without a brick.
const BAKED_EMPTY: u32 = 0xffffffffu;
// The flag of a fine brick's cell word (baked::atlas::FINE_FLAG).
const BAKED_FINE: u32 = 0x80000000u;
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

// Where a point falls in the baked field: the first word of its (coarse) brick's points in
// `baked` (BAKED_EMPTY if its cell has no brick), or for a fine brick the first texel of its
// points in `baked_fine` (fine true); the brick's points per edge, k + 1; the first point of the
// sub-cell around it and the point's place in that sub-cell (each in [0, 1]).
struct BakedSpot {
    base: u32,
    fine: bool,
    texel: vec3<u32>,
    k1: u32,
    i0: vec3<u32>,
    f: vec3<f32>,
}

// The first of the two words of point i (each of i's components in 0..=k) of a coarse spot's brick.
fn baked_word(spot: BakedSpot, i: vec3<u32>) -> u32 {
    return spot.base + 2u * ((i.x * spot.k1 + i.y) * spot.k1 + i.z);
}

// The point stored at word w of `baked` and the next: (sigma_raw, w r, w g, w b),
// w its colour weight.
fn baked_words(w: u32) -> vec4<f32> {
    return vec4<f32>(halves_to_f32(baked[w]), halves_to_f32(baked[w + 1u]));
}

// Cells are the baked field's (G per axis over plane coordinates [-1, 1], the edge cells clamped
// so they stand for everything beyond); inside a cell, k intervals per axis (k_f in a two-level
// field's fine bricks). A cell's word in `baked` is its coarse brick's number, BAKED_EMPTY, or for
// a fine brick BAKED_FINE and its slot in `baked_fine` (10 bits per axis: FineAtlas::index_word).
fn baked_spot(pos: vec3<f32>) -> BakedSpot {
    let g = params.baked_cells;
    let gf = f32(g);
    let s = (plane_coords(pos) + 1.0) * (0.5 * gf);
    let cell_f = clamp(floor(s), vec3<f32>(0.0), vec3<f32>(gf - 1.0));
    let cell = vec3<u32>(cell_f);
    let word = baked[(cell.x * g + cell.y) * g + cell.z];
    let kc1 = params.baked_subdivisions + 1u;
    let fine = word != BAKED_EMPTY && (word & BAKED_FINE) != 0u;
    let k = select(params.baked_subdivisions, params.baked_fine_subdivisions, fine);
    let k1 = k + 1u;
    let base = select(params.baked_values_offset + 2u * word * kc1 * kc1 * kc1, BAKED_EMPTY, word == BAKED_EMPTY);
    let slot = vec3<u32>((word >> 20u) & 0x3ffu, (word >> 10u) & 0x3ffu, word & 0x3ffu);
    let kf = f32(k);
    let local = clamp((s - cell_f) * kf, vec3<f32>(0.0), vec3<f32>(kf));
    let i0_f = min(floor(local), vec3<f32>(kf - 1.0));
    return BakedSpot(base, fine, slot * k1, k1, vec3<u32>(i0_f), local - i0_f);
}

// The eight points of a spot's sub-cell, p<x><y><z>: (sigma_raw, w r, w g, w b).
struct BakedCorners {
    p000: vec4<f32>,
    p001: vec4<f32>,
    p010: vec4<f32>,
    p011: vec4<f32>,
    p100: vec4<f32>,
    p101: vec4<f32>,
    p110: vec4<f32>,
    p111: vec4<f32>,
}

// A spot's eight points (the spot has a brick), loaded with one branch for the level, each corner
// at a constant offset: lavapipe runs a divergent branch's both sides, once per sample here rather
// than once per corner.
fn baked_corners(spot: BakedSpot) -> BakedCorners {
    var q: BakedCorners;
    if (spot.fine) {
        // The atlas holds point i at texel + i.zyx.
        let t = spot.texel + spot.i0.zyx;
        q.p000 = textureLoad(baked_fine, t, 0);
        q.p001 = textureLoad(baked_fine, t + vec3<u32>(1u, 0u, 0u), 0);
        q.p010 = textureLoad(baked_fine, t + vec3<u32>(0u, 1u, 0u), 0);
        q.p011 = textureLoad(baked_fine, t + vec3<u32>(1u, 1u, 0u), 0);
        q.p100 = textureLoad(baked_fine, t + vec3<u32>(0u, 0u, 1u), 0);
        q.p101 = textureLoad(baked_fine, t + vec3<u32>(1u, 0u, 1u), 0);
        q.p110 = textureLoad(baked_fine, t + vec3<u32>(0u, 1u, 1u), 0);
        q.p111 = textureLoad(baked_fine, t + vec3<u32>(1u, 1u, 1u), 0);
    } else {
        // Two words per point; z is the fastest axis (baked_word).
        let w = baked_word(spot, spot.i0);
        let dy = 2u * spot.k1;
        let dx = dy * spot.k1;
        q.p000 = baked_words(w);
        q.p001 = baked_words(w + 2u);
        q.p010 = baked_words(w + dy);
        q.p011 = baked_words(w + dy + 2u);
        q.p100 = baked_words(w + dx);
        q.p101 = baked_words(w + dx + 2u);
        q.p110 = baked_words(w + dx + dy);
        q.p111 = baked_words(w + dx + dy + 2u);
    }
    return q;
}

// Trilinear mix of the eight points at `f` in the sub-cell: z, then y, then x.
fn baked_trilinear(q: BakedCorners, f: vec3<f32>) -> vec4<f32> {
    return mix(
        mix(mix(q.p000, q.p001, f.z), mix(q.p010, q.p011, f.z), f.y),
        mix(mix(q.p100, q.p101, f.z), mix(q.p110, q.p111, f.z), f.y),
        f.x,
    );
}

// The baked raw density at world point `pos` (returned) and its RGB into dst[0].xyz (w = 0).
fn baked_sample(pos: vec3<f32>, dst: ptr<function, array<vec4<f32>, 8>>) -> f32 {
    let spot = baked_spot(pos);
    if (spot.base == BAKED_EMPTY) {
        (*dst)[0] = vec4<f32>(0.0);
        return BAKED_EMPTY_RAW;
    }
    let q = baked_corners(spot);
    let f = spot.f;
    let acc = baked_trilinear(q, f);
    // The colour weights (baked_colour_weight) interpolated the same way.
    let c0 = vec4<f32>(
        baked_colour_weight(q.p000.x),
        baked_colour_weight(q.p010.x),
        baked_colour_weight(q.p100.x),
        baked_colour_weight(q.p110.x),
    );
    let c1 = vec4<f32>(
        baked_colour_weight(q.p001.x),
        baked_colour_weight(q.p011.x),
        baked_colour_weight(q.p101.x),
        baked_colour_weight(q.p111.x),
    );
    let cz = mix(c0, c1, f.z); // (x0 y0, x0 y1, x1 y0, x1 y1)
    let cy = mix(cz.xz, cz.yw, f.y);
    let weight = mix(cy.x, cy.y, f.x);
    (*dst)[0] = vec4<f32>(acc.yzw / weight, 0.0); // un-premultiplied
    return acc.x;
}
