// Entry points. One invocation renders one ray end to end: the coarse density pass and
// inverse-CDF importance draw (sample_importance), then a single streaming pass over the
// merged, sorted samples that decodes each sample once and composites as it goes.
// No per-sample buffers: the coarse list is recomputable from its index and the fine
// depths come out sorted, so merging two sorted lists replaces EG3D's sort.

// Per-invocation scratch: coarse densities -> weights -> pdf -> cdf, and the fine depths.
var<private> scratch: array<f32, MAX_SAMPLES>;
var<private> t_fine: array<f32, MAX_SAMPLES>;

fn density_at(pos: vec3<f32>) -> f32 {
    sample_triplane(pos);
    decode_hidden();
    return decode_density();
}

// sample_importance + sample_pdf: fills t_fine[0..N] (ascending). Returns the number of fine
// samples to use: N, or 0 when the skip "no importance pass for (nearly) empty rays" applies.
fn importance_depths(ray: Ray, ray_index: u32) -> u32 {
    let s = params.depth_resolution;
    let n = params.depth_resolution_importance;
    // 1-2. Raw densities at the coarse samples and the coarse weights w_0..w_{S-2}
    //      (MipRayMarcher2 on the coarse samples), in one front-to-back loop so that early
    //      termination can stop evaluating densities; weights behind it are set to 0.
    var transmittance = 1.0;
    var t_prev = coarse_depth(ray_index, 0u);
    var sigma_prev = density_at(ray.origin + t_prev * ray.dir);
    for (var i = 0u; i + 1u < s; i++) {
        if (transmittance < params.transmittance_threshold) {
            scratch[i] = 0.0;
            continue;
        }
        let t_next = coarse_depth(ray_index, i + 1u);
        let sigma_next = density_at(ray.origin + t_next * ray.dir);
        let alpha = interval_alpha(sigma_prev, sigma_next, t_next - t_prev);
        scratch[i] = alpha * transmittance;
        transmittance = transmit(transmittance, alpha);
        t_prev = t_next;
        sigma_prev = sigma_next;
    }
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
    var n = params.depth_resolution_importance;
    let n_feat = params.feature_channels;
    if (n > 0u) {
        n = importance_depths(ray, ray_index);
    }

    // Streaming composite over the merged samples (coarse k, fine j).
    var k = 0u;
    var j = 0u;
    var transmittance = 1.0;
    var weights_sum = 0.0;
    var depth_acc = 0.0;
    var acc = array<vec4<f32>, 8>();
    var prev_feat = array<vec4<f32>, 8>();
    var cur_feat = array<vec4<f32>, 8>();
    var prev_t = 0.0;
    var prev_sigma = 0.0;
    for (var i = 0u; i < s + n; i++) {
        // Early ray termination (a skip; the exact mode's threshold is 0, so it never fires).
        if (transmittance < params.transmittance_threshold) {
            break;
        }
        var t = 0.0;
        let take_fine = j < n && (k >= s || t_fine[j] < coarse_depth(ray_index, k));
        if (take_fine) {
            t = t_fine[j];
            j++;
        } else {
            t = coarse_depth(ray_index, k);
            k++;
        }
        sample_triplane(ray.origin + t * ray.dir);
        decode_hidden();
        let sigma = decode_density();
        // Only the requested decoder rows: all 32 features, or the 4 that hold RGB.
        // (Branches on a uniform, so every lane takes the same one; loops have constant bounds.)
        if (n_feat == 32u) {
            decode_features(&cur_feat);
        } else if (n_feat > 0u) {
            cur_feat[0] = decode_rgb();
        }
        if (i > 0u) {
            let alpha = interval_alpha(prev_sigma, sigma, t - prev_t);
            let w = alpha * transmittance;
            transmittance = transmit(transmittance, alpha);
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
        prev_t = t;
        prev_sigma = sigma;
        prev_feat = cur_feat;
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
