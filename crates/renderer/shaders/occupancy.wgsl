// Stage: occupancy (docs/occupancy.md). The occupancy grid test, and the walk over a ray's
// merged coarse + fine samples that skips the samples no decoded interval needs.
// needs: params, occupancy_bits, MAX_SAMPLES, Ray, coarse_depth, plane_coords
// provides: occupied, NOT_COARSE, Walk, next_depth, walk_start, walk_advance, walk_to_needed

// Whether `pos` lies in a cell of the occupancy grid that may hold density (always, when the
// skip is off). Outside the box the index clamps to the edge cells, which the bake extends to
// infinity (crates/renderer/src/occupancy.rs).
fn occupied(pos: vec3<f32>) -> bool {
    let g = params.occupancy_resolution;
    if (g == 0u) {
        return true;
    }
    let gf = f32(g);
    let cell = vec3<u32>(clamp(floor((plane_coords(pos) + 1.0) * (0.5 * gf)), vec3<f32>(0.0), vec3<f32>(gf - 1.0)));
    let idx = (cell.x * g + cell.y) * g + cell.z;
    return ((occupancy_bits[idx >> 5u] >> (idx & 31u)) & 1u) != 0u;
}

// Walk.k_cur / k_next of a fine sample.
const NOT_COARSE: u32 = 0xffffffffu;

// A walk over a ray's samples in depth order (coarse k and fine j = t_fine[0..n] merged; n = 0
// walks the coarse samples alone) with the occupancy of samples i - 1, i and i + 1
// (docs/occupancy.md). An interval whose two ends are in empty cells has alpha <=
// occupancy_epsilon and is taken as 0, so sample i needs decoding only if occ_prev, occ_cur or
// occ_next (always, when the skip is off). The passes skip unneeded samples in an inner loop that tests bits only: lavapipe
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
    // Coarse index of the samples at t_cur and t_next (NOT_COARSE for a fine one), and of the
    // depth next_depth returned last.
    k_cur: u32,
    k_next: u32,
    k_last: u32,
}

// The next depth of the merged coarse + fine list (both ascending), advancing k or j.
fn next_depth(
    w: ptr<function, Walk>,
    ray_index: u32,
    n: u32,
    t_fine: ptr<function, array<f32, MAX_SAMPLES>>,
) -> f32 {
    if ((*w).j < n && ((*w).k >= params.depth_resolution || (*t_fine)[(*w).j] < coarse_depth(ray_index, (*w).k))) {
        let t = (*t_fine)[(*w).j];
        (*w).j += 1u;
        (*w).k_last = NOT_COARSE;
        return t;
    }
    let t = coarse_depth(ray_index, (*w).k);
    (*w).k_last = (*w).k;
    (*w).k += 1u;
    return t;
}

fn walk_start(
    ray: Ray,
    ray_index: u32,
    n: u32,
    use_grid: bool,
    t_fine: ptr<function, array<f32, MAX_SAMPLES>>,
) -> Walk {
    var w = Walk(use_grid, 0u, 0u, 0u, params.depth_resolution + n, 0.0, 0.0, false, false, false, NOT_COARSE, NOT_COARSE, NOT_COARSE);
    w.t_cur = next_depth(&w, ray_index, n, t_fine);
    w.k_cur = w.k_last;
    let pos_cur = ray.origin + w.t_cur * ray.dir;
    w.occ_cur = !use_grid || occupied(pos_cur);
    if (w.total > 1u) {
        w.t_next = next_depth(&w, ray_index, n, t_fine);
        w.k_next = w.k_last;
        let pos_next = ray.origin + w.t_next * ray.dir;
        w.occ_next = !use_grid || occupied(pos_next);
    }
    return w;
}

fn walk_advance(
    w: ptr<function, Walk>,
    ray: Ray,
    ray_index: u32,
    n: u32,
    t_fine: ptr<function, array<f32, MAX_SAMPLES>>,
) {
    (*w).occ_prev = (*w).occ_cur;
    (*w).t_cur = (*w).t_next;
    (*w).occ_cur = (*w).occ_next;
    (*w).occ_next = false;
    (*w).k_cur = (*w).k_next;
    (*w).k_next = NOT_COARSE;
    if ((*w).i + 2u < (*w).total) {
        (*w).t_next = next_depth(w, ray_index, n, t_fine);
        (*w).k_next = (*w).k_last;
        let pos = ray.origin + (*w).t_next * ray.dir;
        (*w).occ_next = !(*w).use_grid || occupied(pos);
    }
    (*w).i += 1u;
}

// Moves to the next sample that needs decoding (or past the end).
fn walk_to_needed(
    w: ptr<function, Walk>,
    ray: Ray,
    ray_index: u32,
    n: u32,
    t_fine: ptr<function, array<f32, MAX_SAMPLES>>,
) {
    while ((*w).i < (*w).total && !((*w).occ_prev || (*w).occ_cur || (*w).occ_next)) {
        walk_advance(w, ray, ray_index, n, t_fine);
    }
}
