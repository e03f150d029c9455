// Triplane lookup: EG3D's plane projection (with its axis quirk) and
// grid_sample(bilinear, zeros padding per tap, align_corners=False), averaged over planes.
//
// PLANE_AXES = (x,y), (x,z), (z,x): plane 2 is the transpose of plane 1, not YZ.
// Kept on purpose so EG3D checkpoints render unchanged (eg3d-rendering.md section 2).

// The aggregated 32-channel feature of the current sample.
var<private> feat: array<vec4<f32>, 8>;

fn add_tap(p: u32, x: i32, y: i32, w: f32) {
    let h = i32(params.plane_h);
    let wd = i32(params.plane_w);
    if (x < 0 || y < 0 || x >= wd || y >= h) {
        return; // zeros padding, per tap
    }
    let base = ((p * params.plane_h + u32(y)) * params.plane_w + u32(x)) * 8u;
    for (var q = 0u; q < 8u; q++) {
        feat[q] += w * planes[base + q];
    }
}

// Bilinear tap weights of grid_sample at normalised (u, v) in [-1, 1] for plane p.
fn add_plane(p: u32, u: f32, v: f32) {
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
    add_tap(p, xi, yi, (1.0 - fx) * (1.0 - fy));
    add_tap(p, xi + 1, yi, fx * (1.0 - fy));
    add_tap(p, xi, yi + 1, (1.0 - fx) * fy);
    add_tap(p, xi + 1, yi + 1, fx * fy);
}

// Mean of the three plane features at world point `pos` into `feat`.
fn sample_triplane(pos: vec3<f32>) {
    let q = pos * (2.0 / params.box_warp);
    for (var i = 0u; i < 8u; i++) {
        feat[i] = vec4<f32>(0.0);
    }
    add_plane(0u, q.x, q.y);
    add_plane(1u, q.x, q.z);
    add_plane(2u, q.z, q.x);
    for (var i = 0u; i < 8u; i++) {
        feat[i] = feat[i] / 3.0;
    }
}
