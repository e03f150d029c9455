// Stage: the renderer (lp3d.render.reference.render_reference, lp3d.render.torch_twin.render_rays): the
// render_rays entry point. One invocation renders one ray end to end: the coarse density pass
// and inverse-CDF importance draw (sample_importance), then a single streaming pass over the
// merged, sorted samples that composites as it goes. Each sample is decoded once, as in EG3D: the
// coarse pass keeps what it decoded for the composite (COARSE_CACHE). Both passes run in one
// loop around one sample evaluation (see render_rays).
// The coarse list is recomputable from its index and the fine depths come out sorted, so
// merging two sorted lists replaces EG3D's sort.
// needs: params, out_features, out_depth, out_weights_sum, depth_bounds, MAX_SAMPLES,
// needs: FLAG_OCCUPANCY_COARSE, FLAG_WHITE_BACK, camera_ray, importance_depths, sample_triplane,
// needs: decode, interval_alpha, transmit, Walk, walk_start, walk_advance, walk_to_needed,
// needs: BAKED, baked_sample, FLAG_FULL_WALK
// provides: COARSE_CACHE, Composite, composite_sample, ABSORB_TEST_BELOW, PDF_ABSORBED,
// provides: FEATURE_BOUND, eighth_ulp, composite_absorbed, coarse_absorbed, walk_ends, ray_pixel,
// provides: render_rays

// One loop walks a ray twice: first its coarse samples (the density pass of sample_importance,
// weights into `scratch`), then, after the importance draw, the merged coarse + fine list
// (the streaming composite). Both walks share one sample evaluation (triplane fetch + decoder)
// so the kernel holds a single copy of that code: lavapipe inlines every call, and compile
// time grows with each copy (bench/history/RESULTS.md, "Kernel compile time"). The importance
// draw sits in the outer loop, between the walks: inside the per-sample loop it made every
// sample slower.

// The compositing state of a walk (MipRayMarcher2, front to back).
struct Composite {
    transmittance: f32,
    weights_sum: f32,
    depth_acc: f32,
    prev_t: f32,
    prev_sigma_raw: f32,
    acc: array<vec4<f32>, 8>,
    prev_feat: array<vec4<f32>, 8>,
}

// Adds the interval ending at the walk's current sample (depth t, raw density sigma_raw, features
// cur_feat) to `c`: its weight into `scratch` in the coarse walk, else into the outputs.
fn composite_sample(
    c: ptr<function, Composite>,
    walk: Walk,
    t: f32,
    sigma_raw: f32,
    cur_feat: ptr<function, array<vec4<f32>, 8>>,
    coarse: bool,
    wide: bool,
    scratch: ptr<function, array<f32, MAX_SAMPLES>>,
) {
    if (walk.i > 0u && (walk.occ_prev || walk.occ_cur)) {
        // Both ends were decoded (each is the other's neighbour).
        let alpha = interval_alpha((*c).prev_sigma_raw, sigma_raw, t - (*c).prev_t);
        let w = alpha * (*c).transmittance;
        (*c).transmittance = transmit((*c).transmittance, alpha);
        if (coarse) {
            (*scratch)[walk.i - 1u] = w;
        } else {
            (*c).weights_sum += w;
            (*c).depth_acc += w * (((*c).prev_t + t) * 0.5);
            if (wide) {
                for (var q = 0u; q < 8u; q++) {
                    (*c).acc[q] += w * (((*c).prev_feat[q] + (*cur_feat)[q]) * 0.5);
                }
            } else {
                (*c).acc[0] += w * (((*c).prev_feat[0] + (*cur_feat)[0]) * 0.5);
            }
        }
    }
    (*c).prev_t = t;
    (*c).prev_sigma_raw = sigma_raw;
    if (wide) {
        (*c).prev_feat = *cur_feat;
    } else {
        (*c).prev_feat[0] = (*cur_feat)[0];
    }
}

// Exact early termination: a walk ends once nothing still to come can change its float32 sums,
// so the outputs are bit for bit those of the whole walk (docs/numerics.md, "Exact early
// termination"). It rests on two facts of the float32 arithmetic: the transmittance T never grows
// (each step multiplies it by a factor <= 1), and each later interval's weight, alpha * T with
// alpha <= 1, is at most today's T.

// Below this T the walks test whether the rest is absorbed (a compare per sample above it).
const ABSORB_TEST_BELOW: f32 = 9.5367431640625e-7; // 2^-20
// A coarse weight below 2^-33 leaves a bin's max/avg-pooled weight + PDF_WEIGHT_FLOOR at exactly
// PDF_WEIGHT_FLOOR (half its float32 spacing is 2^-31), as a weight of 0 does.
const PDF_ABSORBED: f32 = 1.16415321826934814453125e-10; // 2^-33
// |a decoded feature| < 1 + SIGMOID_MARGIN, rounded up with room to spare.
const FEATURE_BOUND: f32 = 2.0;

// An eighth of the float32 spacing above |x| (0 for 0 and tiny x): an addend below it leaves x as
// it is, fused or not (the spacing below a power of two is half the one above).
fn eighth_ulp(x: f32) -> f32 {
    let e = bitcast<u32>(x) & 0x7f800000u;
    if (e < (27u << 23u)) {
        return 0.0;
    }
    return bitcast<f32>(e - (26u << 23u));
}

// The composite walk: whether every weight still to come (each <= T) is too small to change the
// weights sum, the depth sum (addends <= T * t_bound) or any output feature (<= T * FEATURE_BOUND).
fn composite_absorbed(c: ptr<function, Composite>, wide: bool, n_feat: u32, t_bound: f32) -> bool {
    let t = (*c).transmittance;
    if (!(t < ABSORB_TEST_BELOW)) {
        return false;
    }
    if (!(t < eighth_ulp((*c).weights_sum) && t * t_bound < eighth_ulp((*c).depth_acc))) {
        return false;
    }
    if (n_feat == 0u) {
        return true;
    }
    // The smallest |sum| among the output channels has the smallest spacing.
    var m = abs((*c).acc[0]);
    if (wide) {
        for (var q = 1u; q < 8u; q++) {
            m = min(m, abs((*c).acc[q]));
        }
    } else {
        // RGB (and one more channel when n_feat says so) in acc[0]; lanes not output do not count.
        m = select(vec4<f32>(1.0), m, vec4<u32>(0u, 1u, 2u, 3u) < vec4<u32>(n_feat));
    }
    return t * FEATURE_BOUND < eighth_ulp(min(min(m.x, m.y), min(m.z, m.w)));
}

// The coarse walk, about to evaluate sample i: whether the weights still to come (w_{i-1} on, each
// <= T) and the two before them are all below PDF_ABSORBED. Every pdf bin that would hold one of
// the weights still to come pools only these, so the importance draw is the same with them as 0.
fn coarse_absorbed(
    t: f32,
    i: u32,
    scratch: ptr<function, array<f32, MAX_SAMPLES>>,
) -> bool {
    if (!(t < PDF_ABSORBED) || i < 3u) {
        return false;
    }
    return (*scratch)[i - 2u] < PDF_ABSORBED && (*scratch)[i - 3u] < PDF_ABSORBED;
}

// Whether the walk about to evaluate sample `walk_i` ends: by the early ray termination skip
// (threshold `thr` > 0), else, when the decoder evaluates the samples, by exact termination
// (unless FLAG_FULL_WALK).
fn walk_ends(
    c: ptr<function, Composite>,
    walk_i: u32,
    coarse: bool,
    wide: bool,
    n_feat: u32,
    thr: f32,
    t_bound: f32,
    scratch: ptr<function, array<f32, MAX_SAMPLES>>,
) -> bool {
    // With the skip's threshold (the viewer's 1e-3), the skip ends a walk long before the exact
    // test would: no need to test. Nor with the baked field, whose un-premultiplied colours have
    // no bound as tight as the decoder's features (and which its skips end anyway).
    if (thr > 0.0 || BAKED || (params.flags & FLAG_FULL_WALK) != 0u) {
        return (*c).transmittance < thr;
    }
    if (coarse) {
        return coarse_absorbed((*c).transmittance, walk_i, scratch);
    }
    return composite_absorbed(c, wide, n_feat, t_bound);
}

// Coarse samples the coarse walk keeps for the composite (the first ones, when a ray has more).
// Not MAX_SAMPLES: lavapipe's compile time grows with the size of a private array, and at
// MAX_SAMPLES the quick kernel would no longer compile quickly (bench/history/RESULTS.md,
// "Kernel steps toward 3×").
const COARSE_CACHE: u32 = 64u;

// The pixel of ray slot `i` (a camera's invocation x). lavapipe runs 8 consecutive invocations in
// lock-step, each loop until the last of the 8 is done, so the 8 are best close together: when the
// side is a multiple of 8, each workgroup of 64 covers an 8 x 8 tile and each 8 a 4 x 2 block of it
// (rows of 8 otherwise).
fn ray_pixel(i: u32) -> u32 {
    let r = params.resolution;
    if ((r & 7u) != 0u) {
        return i;
    }
    let tile = i >> 6u;
    let tiles_x = r >> 3u;
    let lane_group = (i >> 3u) & 7u;
    let lane = i & 7u;
    let x = ((tile % tiles_x) << 3u) + ((lane_group & 1u) << 2u) + (lane & 3u);
    let y = ((tile / tiles_x) << 3u) + ((lane_group >> 1u) << 1u) + (lane >> 2u);
    return y * r + x;
}

@compute @workgroup_size(64)
fn render_rays(@builtin(global_invocation_id) gid: vec3<u32>) {
    let n_pix = params.resolution * params.resolution;
    if (gid.x >= n_pix) {
        return;
    }
    let pixel = ray_pixel(gid.x);
    let cam = params.camera_offset + gid.y;
    let ray_index = cam * n_pix + pixel;
    let out_index = gid.y * n_pix + pixel;
    let ray = camera_ray(cam, pixel);
    let s = params.depth_resolution;
    let n_feat = params.feature_channels;
    // All 32 decoded features per sample, or RGB in the first vec4 only. Never with the baked
    // lookup (RGB only): a constant there, so the compiler drops the 32-feature copies.
    let wide = !BAKED && n_feat == 32u;
    let thr = params.transmittance_threshold;
    // No sample lies farther than this (the depth sum's addends are below T times it).
    let t_bound = 2.0 * (max(abs(params.ray_start), abs(params.ray_end)) + abs(params.jitter_step));
    // Per-invocation scratch: coarse weights -> pdf -> cdf (importance_depths), and the fine
    // depths it draws.
    var scratch = array<f32, MAX_SAMPLES>();
    var t_fine = array<f32, MAX_SAMPLES>();
    // The raw density and decoded features of coarse samples 0..n_cached, kept by the coarse walk
    // for the composite, so that each sample is decoded once, as in EG3D (a coarse sample the
    // occupancy grid skipped ends the run; the composite decodes the ones after it again).
    var cache_sigma_raw = array<f32, COARSE_CACHE>();
    // All 32 features (wide) or RGB alone: two arrays, so that RGB-only pipelines (the baked
    // lookup) keep and clear 1 KiB per ray, not 8.
    var cache_feat = array<array<vec4<f32>, 8>, COARSE_CACHE>();
    var cache_rgb = array<vec4<f32>, COARSE_CACHE>();
    var n_cached = 0u;

    // The coarse walk (only with an importance pass): weights w_0..w_{S-2}
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
    var c = Composite(1.0, 0.0, 0.0, 0.0, 0.0, array<vec4<f32>, 8>(), array<vec4<f32>, 8>());
    // The triplane feature of the current sample (the decoder's input), and its decoded features.
    var feat = array<vec4<f32>, 8>();
    var cur_feat = array<vec4<f32>, 8>();
    // The walks: the coarse one (if any), then the composite. The middle loop holds the one
    // sample evaluation; the outer loop runs it once per walk.
    loop {
        loop {
            // The composite walk's cached coarse samples, in a loop of their own: lavapipe runs
            // 8 rays in lock-step, so each ray composites its cached samples up to its next
            // sample to decode, and the 8 decode together. Early ray termination ends both loops:
            // the skip's (its threshold 0 in exact mode) or the exact one (walk_ends), tested once
            // per sample here: the loop ends either there (`ended`) or at a sample to decode.
            var ended = false;
            loop {
                walk_to_needed(&walk, ray, ray_index, n, &t_fine);
                ended = walk.i >= walk.total || walk_ends(&c, walk.i, coarse, wide, n_feat, thr, t_bound, &scratch);
                if (ended) {
                    break;
                }
                let k = walk.k_cur;
                if (coarse || k >= n_cached) {
                    break;
                }
                if (wide) {
                    cur_feat = cache_feat[k];
                } else {
                    cur_feat[0] = cache_rgb[k];
                }
                composite_sample(&c, walk, walk.t_cur, cache_sigma_raw[k], &cur_feat, false, wide, &scratch);
                walk_advance(&walk, ray, ray_index, n, &t_fine);
            }
            if (ended) {
                break;
            }
            let t = walk.t_cur;
            var sigma_raw: f32;
            if (BAKED) {
                // The baked field's lookup in place of the fetch and the decoder (RGB only).
                sigma_raw = baked_sample(ray.origin + t * ray.dir, &cur_feat);
            } else {
                sample_triplane(ray.origin + t * ray.dir, &feat);
                // Only the requested decoder rows: all 32 features or the 4 that hold RGB (also in
                // the coarse walk, for the cache).
                sigma_raw = decode(n_feat, &feat, &cur_feat);
            }
            if (coarse && walk.k_cur == n_cached && n_cached < COARSE_CACHE) {
                cache_sigma_raw[n_cached] = sigma_raw;
                if (wide) {
                    cache_feat[n_cached] = cur_feat;
                } else {
                    cache_rgb[n_cached] = cur_feat[0];
                }
                n_cached++;
            }
            composite_sample(&c, walk, t, sigma_raw, &cur_feat, coarse, wide, &scratch);
            walk_advance(&walk, ray, ray_index, n, &t_fine);
        }
        if (!coarse) {
            break;
        }
        // End of the coarse walk: draw the fine depths, then composite the merged list,
        // skipping as the coarse walk does.
        n = importance_depths(ray_index, c.transmittance, &scratch, &t_fine);
        coarse = false;
        walk = walk_start(ray, ray_index, n, true, &t_fine);
        c.transmittance = 1.0;
        c.prev_t = 0.0;
        c.prev_sigma_raw = 0.0;
    }
    let weights_sum = c.weights_sum;
    let depth_acc = c.depth_acc;

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
        let v = c.acc[ch / 4u][ch % 4u] + background;
        out_features[(gid.y * n_feat + ch) * n_pix + pixel] = v * 2.0 - 1.0;
    }
}
