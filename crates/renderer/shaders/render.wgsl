// Stage: the renderer (lp3d.reference.render_reference, lp3d.render_torch.render_rays): the
// render_rays entry point. One invocation renders one ray end to end: the coarse density pass
// and inverse-CDF importance draw (sample_importance), then a single streaming pass over the
// merged, sorted samples that decodes each sample once and composites as it goes. Both passes
// run in one loop around one sample evaluation (see render_rays).
// No per-sample buffers: the coarse list is recomputable from its index and the fine
// depths come out sorted, so merging two sorted lists replaces EG3D's sort.
// needs: params, out_features, out_depth, out_weights_sum, depth_bounds, MAX_SAMPLES,
// needs: FLAG_OCCUPANCY_COARSE, FLAG_WHITE_BACK, camera_ray, importance_depths, sample_triplane,
// needs: decode, interval_alpha, transmit, walk_start, walk_advance, walk_to_needed
// provides: render_rays

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
    // Per-invocation scratch: coarse weights -> pdf -> cdf (importance_depths), and the fine
    // depths it draws.
    var scratch = array<f32, MAX_SAMPLES>();
    var t_fine = array<f32, MAX_SAMPLES>();

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
    var walk = walk_start(ray, ray_index, 0u, !coarse || (params.flags & FLAG_OCCUPANCY_COARSE) != 0u, &t_fine);
    var transmittance = 1.0;
    var weights_sum = 0.0;
    var depth_acc = 0.0;
    var acc = array<vec4<f32>, 8>();
    // The triplane feature of the current sample (the decoder's input).
    var feat = array<vec4<f32>, 8>();
    var prev_feat = array<vec4<f32>, 8>();
    var cur_feat = array<vec4<f32>, 8>();
    var prev_t = 0.0;
    var prev_sigma = 0.0;
    // The walks: the coarse one (if any), then the composite. The inner loop holds the one
    // sample evaluation; the outer loop runs it once per walk.
    loop {
        loop {
            walk_to_needed(&walk, ray, ray_index, n, &t_fine);
            // Early ray termination (a skip; the exact mode's threshold is 0, so it never fires).
            if (walk.i >= walk.total || transmittance < params.transmittance_threshold) {
                break;
            }
            let t = walk.t_cur;
            sample_triplane(ray.origin + t * ray.dir, &feat);
            // Only the requested decoder rows: none in the coarse walk, else all 32 features or
            // the 4 that hold RGB.
            let sigma = decode(select(n_feat, 0u, coarse), &feat, &cur_feat);
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
            walk_advance(&walk, ray, ray_index, n, &t_fine);
        }
        if (!coarse) {
            break;
        }
        // End of the coarse walk: draw the fine depths, then composite the merged list,
        // skipping as the coarse walk does.
        n = importance_depths(ray_index, transmittance, &scratch, &t_fine);
        coarse = false;
        walk = walk_start(ray, ray_index, n, true, &t_fine);
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
