// Depths along a ray: EG3D's stratified coarse samples, the counter-based jitter RNG
// (docs/sampling-rng.md) and the importance draw's uniforms.

fn pcg_hash(v: u32) -> u32 {
    let state = v * 747796405u + 2891336453u;
    let word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

fn rand_u32(ray: u32, stream: u32, k: u32) -> u32 {
    return pcg_hash(pcg_hash(pcg_hash(params.seed ^ (stream * 0x9E3779B9u)) + ray) + k);
}

fn uniform01(x: u32) -> f32 {
    return f32(x >> 8u) * (1.0 / 16777216.0);
}

fn jittered() -> bool {
    return (params.flags & FLAG_JITTER) != 0u;
}

// torch.linspace(a, b, n)[k] in float32: single-rounding evaluation from each end.
fn linspace_at(k: u32, n: u32, a: f32, b: f32, step: f32) -> f32 {
    if (k < n / 2u) {
        return fma(f32(k), step, a);
    }
    return fma(-f32(n - 1u - k), step, b);
}

// Coarse depth k of a ray (sample_stratified).
fn coarse_depth(ray_index: u32, k: u32) -> f32 {
    let s = params.depth_resolution;
    var t = linspace_at(k, s, params.ray_start, params.ray_end, params.lin_step);
    if (jittered()) {
        t = t + uniform01(rand_u32(ray_index, 0u, k)) * params.jitter_step;
    }
    return t;
}

// Coarse interval midpoint k: the bins of sample_pdf.
fn coarse_mid(ray_index: u32, k: u32) -> f32 {
    return 0.5 * (coarse_depth(ray_index, k) + coarse_depth(ray_index, k + 1u));
}

// -log(1 - U) for the exponential-spacings draw of sorted uniforms.
fn spacing(ray_index: u32, j: u32) -> f32 {
    return -log(1.0 - uniform01(rand_u32(ray_index, 1u, j)));
}

// Sum of the N + 1 spacings; u_j = (e_0 + ... + e_j) / total.
fn spacing_total(ray_index: u32) -> f32 {
    var total = 0.0;
    for (var j = 0u; j <= params.depth_resolution_importance; j++) {
        total += spacing(ray_index, j);
    }
    return total;
}
