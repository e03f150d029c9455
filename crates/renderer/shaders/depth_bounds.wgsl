// Stage: the depth range of EG3D's depth clamp (lp3d.render.torch_twin.clamp_depth): an entry point
// run once over all cameras before render_rays.
// needs: params, depth_bounds, coarse_depth, jittered
// provides: depth_bounds_pass

// Batch-global [min, max] over every ray's coarse depths (fine depths lie between a
// ray's first and last coarse depth). Run once over all cameras before render_rays.
@compute @workgroup_size(64)
fn depth_bounds_pass(@builtin(global_invocation_id) gid: vec3<u32>) {
    let n_pix = params.resolution * params.resolution;
    let pixel = gid.x;
    if (pixel >= n_pix || gid.y >= params.n_cameras) {
        return;
    }
    // Without jitter every ray has the same coarse depths: the first ray's range is the batch's.
    if (!jittered() && (pixel != 0u || gid.y != 0u)) {
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
