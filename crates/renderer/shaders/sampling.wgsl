// Stage: sampling (lp3d.render.reference.sample_stratified, sample_importance, sample_pdf). Depths
// along a ray: EG3D's stratified coarse samples, the counter-based jitter RNG
// (docs/sampling-rng.md) and the importance draw (inverse CDF of the coarse weights).
// needs: params, FLAG_JITTER, MAX_SAMPLES
// provides: PDF_WEIGHT_FLOOR, PDF_EPS, pcg_hash, rand_u32, uniform01, jittered, linspace_at,
// provides: coarse_depth, coarse_mid, spacing, spacing_total, importance_depths

// EG3D's sample_importance: added to the smoothed coarse weights (after max_pool1d, avg_pool1d).
const PDF_WEIGHT_FLOOR: f32 = 0.01;
// EG3D's sample_pdf eps: added to every bin weight, and the smallest CDF step the inverse-CDF
// interpolation divides by (a narrower step divides by 1).
const PDF_EPS: f32 = 1e-5;

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

// Steps 3-5 of sample_importance + sample_pdf, after the coarse walk left the coarse weights
// w_0..w_{S-2} in `scratch` and its transmittance in `transmittance`: fills t_fine[0..N]
// (ascending), using `scratch` for the pdf and cdf. Returns the number of fine samples to use:
// N, or 0 when the skip "no importance pass for (nearly) empty rays" applies.
fn importance_depths(
    ray_index: u32,
    transmittance: f32,
    scratch: ptr<function, array<f32, MAX_SAMPLES>>,
    t_fine: ptr<function, array<f32, MAX_SAMPLES>>,
) -> u32 {
    let s = params.depth_resolution;
    let n = params.depth_resolution_importance;
    if (1.0 - transmittance < params.empty_threshold) {
        return 0u;
    }
    // 3. max_pool1d(2, 1, pad 1) -> avg_pool1d(2, 1) -> + PDF_WEIGHT_FLOOR, keeping
    //    a[1:S-2] (S - 3 bin weights), then sample_pdf's + PDF_EPS. In place, front to back.
    //    Weights k + 1 and k + 2 are carried in registers (a and b), so each bin loads one weight.
    let n_bins = s - 3u;
    var total = 0.0;
    var a = (*scratch)[0];
    var b = (*scratch)[1];
    for (var k = 0u; k < n_bins; k++) {
        let c = (*scratch)[k + 2u];
        let bin = (max(a, b) + max(b, c)) * 0.5 + PDF_WEIGHT_FLOOR + PDF_EPS;
        (*scratch)[k] = bin;
        total += bin;
        a = b;
        b = c;
    }
    // 4. cdf = [0, cumsum(pdf)]: S - 2 entries, in place.
    var c = 0.0;
    for (var k = 0u; k < n_bins; k++) {
        let pdf = (*scratch)[k] / total;
        (*scratch)[k] = c;
        c += pdf;
    }
    (*scratch)[n_bins] = c;
    // 5. Inverse CDF at ascending u: searchsorted(right=True) advances monotonically.
    var e_total = 1.0;
    var e_sum = 0.0;
    if (jittered()) {
        e_total = spacing_total(ray_index);
    }
    //    The cdf at `below` and `above` is carried in registers (c0, c1): each step of idx loads one.
    var idx = 0u;
    var c0 = (*scratch)[0];
    var c1 = c0;
    for (var j = 0u; j < n; j++) {
        var u = 0.0;
        if (jittered()) {
            e_sum += spacing(ray_index, j);
            u = e_sum / e_total;
        } else {
            u = linspace_at(j, n, 0.0, 1.0, params.u_step);
        }
        while (idx <= n_bins && c1 <= u) {
            idx++;
            c0 = c1;
            if (idx <= n_bins) {
                c1 = (*scratch)[idx];
            }
        }
        let below = max(idx, 1u) - 1u;
        let above = min(idx, n_bins);
        var denom = c1 - c0;
        if (denom < PDF_EPS) {
            denom = 1.0;
        }
        let b0 = coarse_mid(ray_index, below);
        let b1 = coarse_mid(ray_index, above);
        (*t_fine)[j] = b0 + (u - c0) / denom * (b1 - b0);
    }
    return n;
}
