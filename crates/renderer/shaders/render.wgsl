// Entry points. One invocation renders one ray end to end: the coarse density pass and
// inverse-CDF importance draw (sample_importance), then a single streaming pass over the
// merged, sorted samples that decodes each sample once and composites as it goes. Both passes
// run in one loop around one sample evaluation (see render_rays).
// No per-sample buffers: the coarse list is recomputable from its index and the fine
// depths come out sorted, so merging two sorted lists replaces EG3D's sort.

// Per-invocation scratch: coarse densities -> weights -> pdf -> cdf, and the fine depths.
var<private> scratch: array<f32, MAX_SAMPLES>;
var<private> t_fine: array<f32, MAX_SAMPLES>;

// A walk over a ray's samples in depth order (coarse k and fine j merged; n = 0 walks the
// coarse samples alone) with the occupancy of samples i - 1, i and i + 1 (docs/occupancy.md).
// An interval whose two ends are in empty cells has alpha <= occupancy_epsilon and is taken as
// 0, so sample i needs decoding only if occ_prev, occ_cur or occ_next (always, when the skip
// is off). The passes skip unneeded samples in an inner loop that tests bits only: lavapipe
// runs 8 rays in lock-step and executes an `if` body unless all 8 skip it, whereas a loop lets
// each ray move on to its own next needed sample.
struct Walk {
    // Test the occupancy grid (else every sample counts as occupied).
    use_grid: bool,
    i: u32,
    k: u32,
    j: u32,
    total: u32,
    t_cur: f32,
    t_next: f32,
    occ_prev: bool,
    occ_cur: bool,
    occ_next: bool,
}

// The next depth of the merged coarse + fine list (both ascending), advancing k or j.
fn next_depth(w: ptr<function, Walk>, ray_index: u32, n: u32) -> f32 {
    if ((*w).j < n && ((*w).k >= params.depth_resolution || t_fine[(*w).j] < coarse_depth(ray_index, (*w).k))) {
        let t = t_fine[(*w).j];
        (*w).j += 1u;
        return t;
    }
    let t = coarse_depth(ray_index, (*w).k);
    (*w).k += 1u;
    return t;
}

fn walk_start(ray: Ray, ray_index: u32, n: u32, use_grid: bool) -> Walk {
    var w = Walk(use_grid, 0u, 0u, 0u, params.depth_resolution + n, 0.0, 0.0, false, false, false);
    w.t_cur = next_depth(&w, ray_index, n);
    w.occ_cur = !use_grid || occupied(ray.origin + w.t_cur * ray.dir);
    if (w.total > 1u) {
        w.t_next = next_depth(&w, ray_index, n);
        w.occ_next = !use_grid || occupied(ray.origin + w.t_next * ray.dir);
    }
    return w;
}

fn walk_advance(w: ptr<function, Walk>, ray: Ray, ray_index: u32, n: u32) {
    (*w).occ_prev = (*w).occ_cur;
    (*w).t_cur = (*w).t_next;
    (*w).occ_cur = (*w).occ_next;
    (*w).occ_next = false;
    if ((*w).i + 2u < (*w).total) {
        (*w).t_next = next_depth(w, ray_index, n);
        (*w).occ_next = !(*w).use_grid || occupied(ray.origin + (*w).t_next * ray.dir);
    }
    (*w).i += 1u;
}

// Moves to the next sample that needs decoding (or past the end).
fn walk_to_needed(w: ptr<function, Walk>, ray: Ray, ray_index: u32, n: u32) {
    while ((*w).i < (*w).total && !((*w).occ_prev || (*w).occ_cur || (*w).occ_next)) {
        walk_advance(w, ray, ray_index, n);
    }
}

// Steps 3-5 of sample_importance + sample_pdf, after the coarse pass left the coarse weights
// w_0..w_{S-2} in `scratch` and its transmittance in `transmittance`: fills t_fine[0..N]
// (ascending). Returns the number of fine samples to use: N, or 0 when the skip "no importance
// pass for (nearly) empty rays" applies.
fn importance_depths(ray_index: u32, transmittance: f32) -> u32 {
    let s = params.depth_resolution;
    let n = params.depth_resolution_importance;
    if (1.0 - transmittance < params.empty_threshold) {
        return 0u;
    }
    // 3. max_pool1d(2, 1, pad 1) -> avg_pool1d(2, 1) -> + 0.01, keeping a[1:S-2]
    //    (S - 3 bin weights), then sample_pdf's + 1e-5. In place, front to back.
    let n_bins = s - 3u;
    var total = 0.0;
    for (var k = 0u; k < n_bins; k++) {
        let pw = (max(scratch[k], scratch[k + 1u]) + max(scratch[k + 1u], scratch[k + 2u])) * 0.5 + 0.01;
        scratch[k] = pw + 1e-5;
        total += scratch[k];
    }
    // 4. cdf = [0, cumsum(pdf)]: S - 2 entries, in place.
    var c = 0.0;
    for (var k = 0u; k < n_bins; k++) {
        let pdf = scratch[k] / total;
        scratch[k] = c;
        c += pdf;
    }
    scratch[n_bins] = c;
    // 5. Inverse CDF at ascending u: searchsorted(right=True) advances monotonically.
    var e_total = 1.0;
    var e_sum = 0.0;
    if (jittered()) {
        e_total = spacing_total(ray_index);
    }
    var idx = 0u;
    for (var j = 0u; j < n; j++) {
        var u = 0.0;
        if (jittered()) {
            e_sum += spacing(ray_index, j);
            u = e_sum / e_total;
        } else {
            u = linspace_at(j, n, 0.0, 1.0, params.u_step);
        }
        while (idx <= n_bins && scratch[idx] <= u) {
            idx++;
        }
        let below = max(idx, 1u) - 1u;
        let above = min(idx, n_bins);
        let c0 = scratch[below];
        var denom = scratch[above] - c0;
        if (denom < 1e-5) {
            denom = 1.0;
        }
        let b0 = coarse_mid(ray_index, below);
        let b1 = coarse_mid(ray_index, above);
        t_fine[j] = b0 + (u - c0) / denom * (b1 - b0);
    }
    return n;
}

// One loop walks a ray twice: first its coarse samples (the density pass of sample_importance,
// weights into `scratch`), then, after the importance draw, the merged coarse + fine list
// (the streaming composite). Both walks share one sample evaluation (triplane fetch + decoder)
// so the kernel holds a single copy of that code: lavapipe inlines every call, and compile
// time grows with each copy (bench/RESULTS.md, "Kernel compile time"). The importance draw
// sits in the outer loop, between the walks: inside the per-sample loop it made every sample
// slower.
@compute @workgroup_size(64)
fn render_rays(@builtin(global_invocation_id) gid: vec3<u32>) {
    let n_pix = params.resolution * params.resolution;
    let pixel = gid.x;
    if (pixel >= n_pix) {
        return;
    }
    let cam = params.camera_offset + gid.y;
    let ray_index = cam * n_pix + pixel;
    let out_index = gid.y * n_pix + pixel;
    let ray = camera_ray(cam, pixel);
    let s = params.depth_resolution;
    let n_feat = params.feature_channels;

    // The coarse walk (only with an importance pass): densities alone, weights w_0..w_{S-2}
    // (MipRayMarcher2 on the coarse samples) into `scratch`, front to back so that early
    // termination can stop evaluating densities; weights behind it, and of intervals the
    // occupancy grid skips, stay 0. Skipping here too is faster but moves the importance
    // samples (docs/occupancy.md).
    var coarse = params.depth_resolution_importance > 0u;
    if (coarse) {
        for (var i = 0u; i + 1u < s; i++) {
            scratch[i] = 0.0;
        }
    }
    // Fine samples in the current walk (none in the coarse walk).
    var n = 0u;
    var walk = walk_start(ray, ray_index, 0u, !coarse || (params.flags & FLAG_OCCUPANCY_COARSE) != 0u);
    var transmittance = 1.0;
    var weights_sum = 0.0;
    var depth_acc = 0.0;
    var acc = array<vec4<f32>, 8>();
    var prev_feat = array<vec4<f32>, 8>();
    var cur_feat = array<vec4<f32>, 8>();
    var prev_t = 0.0;
    var prev_sigma = 0.0;
    // The walks: the coarse one (if any), then the composite. The inner loop holds the one
    // sample evaluation; the outer loop runs it once per walk.
    loop {
        loop {
            walk_to_needed(&walk, ray, ray_index, n);
            // Early ray termination (a skip; the exact mode's threshold is 0, so it never fires).
            if (walk.i >= walk.total || transmittance < params.transmittance_threshold) {
                break;
            }
            let t = walk.t_cur;
            sample_triplane(ray.origin + t * ray.dir);
            // Only the requested decoder rows: none in the coarse walk, else all 32 features or
            // the 4 that hold RGB.
            let sigma = decode(select(n_feat, 0u, coarse), &cur_feat);
            if (walk.i > 0u && (walk.occ_prev || walk.occ_cur)) {
                // Both ends were decoded (each is the other's neighbour).
                let alpha = interval_alpha(prev_sigma, sigma, t - prev_t);
                let w = alpha * transmittance;
                transmittance = transmit(transmittance, alpha);
                if (coarse) {
                    scratch[walk.i - 1u] = w;
                } else {
                    weights_sum += w;
                    depth_acc += w * ((prev_t + t) * 0.5);
                    if (n_feat == 32u) {
                        for (var q = 0u; q < 8u; q++) {
                            acc[q] += w * ((prev_feat[q] + cur_feat[q]) * 0.5);
                        }
                    } else {
                        acc[0] += w * ((prev_feat[0] + cur_feat[0]) * 0.5);
                    }
                }
            }
            prev_t = t;
            prev_sigma = sigma;
            prev_feat = cur_feat;
            walk_advance(&walk, ray, ray_index, n);
        }
        if (!coarse) {
            break;
        }
        // End of the coarse walk: draw the fine depths, then composite the merged list,
        // skipping as the coarse walk does.
        n = importance_depths(ray_index, transmittance);
        coarse = false;
        walk = walk_start(ray, ray_index, n, true);
        transmittance = 1.0;
        prev_t = 0.0;
        prev_sigma = 0.0;
    }

    // Depth: EG3D turns 0/0 into +inf and clamps to the batch-global depth range, so a ray
    // with no weight gets the range's maximum.
    let lo = bitcast<f32>(atomicLoad(&depth_bounds[0]));
    let hi = bitcast<f32>(atomicLoad(&depth_bounds[1]));
    var depth = hi;
    if (weights_sum > 0.0) {
        depth = clamp(depth_acc / weights_sum, lo, hi);
    }
    out_depth[out_index] = depth;
    // A sum of weights that telescopes to 1 - T can round a few ulps above 1 in float32
    // (1.0000005 at 48+48); the output is clamped to its mathematical range (docs/numerics.md).
    out_weights_sum[out_index] = min(weights_sum, 1.0);

    var background = 0.0;
    if ((params.flags & FLAG_WHITE_BACK) != 0u) {
        background = 1.0 - weights_sum;
    }
    for (var ch = 0u; ch < n_feat; ch++) {
        let v = acc[ch / 4u][ch % 4u] + background;
        out_features[(gid.y * n_feat + ch) * n_pix + pixel] = v * 2.0 - 1.0;
    }
}

// Batch-global [min, max] over every ray's coarse depths (fine depths lie between a
// ray's first and last coarse depth). Run once over all cameras before render_rays.
@compute @workgroup_size(64)
fn depth_bounds_pass(@builtin(global_invocation_id) gid: vec3<u32>) {
    let n_pix = params.resolution * params.resolution;
    let pixel = gid.x;
    if (pixel >= n_pix || gid.y >= params.n_cameras) {
        return;
    }
    let ray_index = gid.y * n_pix + pixel;
    var lo = coarse_depth(ray_index, 0u);
    var hi = lo;
    for (var k = 1u; k < params.depth_resolution; k++) {
        let t = coarse_depth(ray_index, k);
        lo = min(lo, t);
        hi = max(hi, t);
    }
    atomicMin(&depth_bounds[0], bitcast<u32>(lo));
    atomicMax(&depth_bounds[1], bitcast<u32>(hi));
}
