//! The baked field (`docs/baked.md`): the decoder's raw density and RGB, computed once at the
//! points of a fine grid and looked up (trilinearly) in place of the triplane fetch and the
//! decoder. A head being looked at does not change, so a viewer or an orbit video decodes it
//! once instead of once per sample of every frame.
//!
//! Layout: G³ cells over the scene box, each split into k³ sub-cells. The cells are the
//! occupancy grid's (`crate::occupancy`), or, when that grid is finer than [`TARGET_CELLS`], blocks
//! of its cells (their bound the largest of theirs): a brick's (k + 1)³ points repeat its faces,
//! and larger cells repeat fewer. A cell gets a *brick*, its (k + 1)³ corner points, when the
//! occupancy skip could decode a sample in it: when it is occupied at the skip's threshold, or
//! within one sample interval of an occupied cell (a sample next to an occupied one is decoded
//! too). Elsewhere the field is empty, as the skip takes it. Each point is (sigma_raw, w r, w g,
//! w b) as float16, 8 bytes: the RGB premultiplied by the point's colour weight w
//! (`baked_colour_weight` in `baked.wgsl`), so that corners in empty space do not tint a surface.
//! Point (a, b, c) of brick n is value `((n (k+1) + a)(k+1) + b)(k+1) + c`; its plane
//! coordinates are `-1 + 2 (cell k + (a, b, c)) / (G k)`.
//!
//! A *two-level* field (`BakeSpec::fine_subdivisions` > 0) splits the bricks a surface crosses,
//! or whose colour changes just under one ([`needs_fine`], judged on their k-point values), finer,
//! into k_f³ sub-cells: its bricks are numbered in cell order, first the N_c coarse ones, then the
//! fine ones, whose (k_f + 1)³ points follow all the coarse points. A brick number n >= N_c is fine
//! brick n - N_c. On the GPU the fine points live in a 3D texture ([`atlas`]), not after the
//! coarse ones in the field's buffer (a storage binding is too small for them), and a fine brick's
//! cell holds its place in that texture.

pub mod atlas;

use crate::error::{Error, Result};
use crate::occupancy::Occupancy;

/// Largest accepted points per cell edge, k.
pub const MAX_SUBDIVISIONS: u32 = 8;
/// Largest accepted points per cell edge of a two-level field's fine bricks, k_f.
pub const MAX_FINE_SUBDIVISIONS: u32 = 16;
/// A brick is crossed by a surface when its raw density rises above this at one of its points
/// ([`needs_fine`]) ...
pub const CROSSED_DENSE: f32 = 10.0;
/// ... and falls below this at another (`bench/baked_resolution.py` chose both: the fewest bricks
/// that hold the error of a uniform field as fine, `bench/history/RESULTS.md`, "How fine a
/// field reaches exact 48+48's error").
pub const CROSSED_SOLID: f32 = 50.0;
/// A brick whose raw density stays above [`CROSSED_SOLID`] but falls below this somewhere lies in
/// the shell just under a surface, still seen through it (at 48+48 a ray's transmittance falls to
/// 1e-3 over a few sub-cells there) ...
pub const FINE_SHELL: f32 = 200.0;
/// ... and is made fine too when the colour of its dense points (raw density above
/// [`CROSSED_DENSE`]) spans more than this in one channel (of the decoder's [0, 1] RGB): an
/// eyebrow's or a lip's edge under the skin, which k points per cell edge blur (`bench/history/RESULTS.md`,
/// "Colour edges under a surface").
pub const FINE_COLOUR_STEP: f32 = 0.1;
/// Every point's colour weight is at least this (`BAKED_COLOUR_FLOOR` in `baked.wgsl`) ...
pub const COLOUR_FLOOR: f32 = 0.03;
/// ... and climbs linearly with its raw density above it, by 1 at this one (`BAKED_COLOUR_RAMP`).
pub const COLOUR_RAMP: f32 = 50.0;
/// `index` of a cell without a brick (`BAKED_EMPTY` in `shaders/baked.wgsl`).
pub const EMPTY: u32 = u32::MAX;
/// Bytes per baked point: four float16.
pub const POINT_BYTES: usize = 8;
/// The baked field's cells per axis: the occupancy grid's G divided by the largest factor that
/// leaves at least this many (64 -> 32; 32 -> 32; 48 -> 48).
pub const TARGET_CELLS: usize = 32;

/// Cells per axis of a field baked from an occupancy grid of `g` cells per axis.
pub fn baked_cells(g: usize) -> usize {
    let factor = (1..=(g / TARGET_CELLS).max(1)).rev().find(|f| g % f == 0).unwrap_or(1);
    g / factor
}

/// What a bake covers: `subdivisions` points per cell edge, the cells the occupancy skip keeps
/// at `epsilon` for intervals up to `max_delta` long.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BakeSpec {
    pub subdivisions: u32,
    /// Points per cell edge of the bricks [`needs_fine`] picks; 0 = one level.
    pub fine_subdivisions: u32,
    pub epsilon: f32,
    pub max_delta: f64,
}

impl BakeSpec {
    /// Whether a field baked for `self` serves a render that needs `need`: the same points per
    /// cell, and every cell that render could decode has a brick (a larger epsilon or shorter
    /// intervals keep fewer cells).
    pub fn covers(&self, need: &BakeSpec) -> bool {
        self.subdivisions == need.subdivisions
            && self.fine_subdivisions == need.fine_subdivisions
            && self.epsilon <= need.epsilon
            && self.max_delta >= need.max_delta
    }
}

/// Which cells hold bricks: the CPU half of a bake.
#[derive(Debug, Clone, PartialEq)]
pub struct BrickLayout {
    /// Cells per axis, G (the occupancy grid's).
    pub cells: usize,
    /// G³ entries, `(ix * G + iy) * G + iz`: the cell's brick number, or [`EMPTY`].
    pub index: Vec<u32>,
    /// The flat cell index of each brick, in brick order.
    pub brick_cells: Vec<u32>,
}

impl BrickLayout {
    /// The bricks of a field baked for `spec` from the occupancy `grid` of a scene whose box
    /// is `box_warp` wide.
    pub fn new(grid: &Occupancy, spec: &BakeSpec, box_warp: f32) -> Result<BrickLayout> {
        if !(1..=MAX_SUBDIVISIONS).contains(&spec.subdivisions) {
            return Err(Error::invalid(
                "baked_subdivisions",
                format!("must be in [1, {MAX_SUBDIVISIONS}], got {}", spec.subdivisions),
            ));
        }
        let g = baked_cells(grid.resolution);
        let threshold = Occupancy::raw_threshold(spec.epsilon as f64, spec.max_delta);
        let occupied: Vec<bool> = coarse_bounds(grid, g).iter().map(|&b| b as f64 > threshold).collect();
        // Two samples one interval apart lie at most this many cells apart on each axis.
        let cell_width = box_warp as f64 / g as f64;
        let reach = ((spec.max_delta / cell_width).ceil() as usize).min(g);
        let kept = dilate(&occupied, g, reach);
        let mut index = vec![EMPTY; g * g * g];
        let mut brick_cells = Vec::new();
        for (cell, _) in kept.iter().enumerate().filter(|(_, &k)| k) {
            index[cell] = brick_cells.len() as u32;
            brick_cells.push(cell as u32);
        }
        Ok(BrickLayout { cells: g, index, brick_cells })
    }

    /// Points per brick, (k + 1)³.
    pub fn points_per_brick(subdivisions: u32) -> usize {
        (subdivisions as usize + 1).pow(3)
    }

    /// The two-level layout of these bricks, the ones `is_fine` (in brick order) made fine: the
    /// coarse ones keep their order as bricks 0..N_c, the fine ones follow as N_c.. .
    pub fn two_level(&self, is_fine: &[bool]) -> TwoLevelLayout {
        assert_eq!(is_fine.len(), self.brick_cells.len());
        let mut index = vec![EMPTY; self.index.len()];
        let (mut coarse, mut fine) = (Vec::new(), Vec::new());
        for (brick, &cell) in self.brick_cells.iter().enumerate() {
            if is_fine[brick] {
                fine.push(cell);
            } else {
                index[cell as usize] = coarse.len() as u32;
                coarse.push(brick as u32);
            }
        }
        for (j, &cell) in fine.iter().enumerate() {
            index[cell as usize] = (coarse.len() + j) as u32;
        }
        TwoLevelLayout { index, coarse_bricks: coarse, fine_cells: fine }
    }
}

/// A two-level field's bricks ([`BrickLayout::two_level`]).
#[derive(Debug, Clone, PartialEq)]
pub struct TwoLevelLayout {
    /// G³ entries: the cell's brick number (coarse 0..N_c, then fine), or [`EMPTY`].
    pub index: Vec<u32>,
    /// The coarse bricks, as numbers of the one-level layout they came from (N_c).
    pub coarse_bricks: Vec<u32>,
    /// The flat cell index of each fine brick, in fine-brick order.
    pub fine_cells: Vec<u32>,
}

/// Whether a two-level field makes a brick fine, from its points' stored values (sigma_raw,
/// w r, w g, w b; [`colour_weight`]): when a surface crosses it (a raw density above
/// [`CROSSED_DENSE`] and one below [`CROSSED_SOLID`]), or when it lies in the shell under one
/// (one below [`FINE_SHELL`]) and its dense points' colour spans more than [`FINE_COLOUR_STEP`].
/// A brick that stays below [`CROSSED_DENSE`] is empty or faint there; one that stays above
/// [`FINE_SHELL`] is deep inside the head, where its colour is hidden.
pub fn needs_fine(points: impl IntoIterator<Item = [f32; 4]>) -> bool {
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    let (mut rgb_lo, mut rgb_hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for [sigma, r, g, b] in points {
        lo = lo.min(sigma);
        hi = hi.max(sigma);
        if sigma > CROSSED_DENSE {
            let w = colour_weight(sigma);
            for (c, v) in [r, g, b].into_iter().enumerate() {
                rgb_lo[c] = rgb_lo[c].min(v / w);
                rgb_hi[c] = rgb_hi[c].max(v / w);
            }
        }
    }
    let crossed = hi > CROSSED_DENSE && lo < CROSSED_SOLID;
    let colour_edge = (0..3).any(|c| rgb_hi[c] - rgb_lo[c] > FINE_COLOUR_STEP);
    crossed || (lo < FINE_SHELL && colour_edge)
}

/// A baked point's colour weight for its raw density (`baked_colour_weight` in `baked.wgsl`,
/// `lp3d.render.baked.colour_weight`).
pub fn colour_weight(sigma_raw: f32) -> f32 {
    COLOUR_FLOOR + (sigma_raw / COLOUR_RAMP).clamp(0.0, 1.0)
}

/// The bound of each of `g`³ blocks of `grid`'s cells (`g` divides its resolution): the largest
/// of its cells' bounds, a bound on the block.
fn coarse_bounds(grid: &Occupancy, g: usize) -> Vec<f32> {
    let fine = grid.resolution;
    let f = fine / g;
    let mut out = vec![f32::NEG_INFINITY; g * g * g];
    for (i, &b) in grid.bound.iter().enumerate() {
        let (x, y, z) = (i / (fine * fine), (i / fine) % fine, i % fine);
        let slot = &mut out[((x / f) * g + y / f) * g + z / f];
        *slot = slot.max(b);
    }
    out
}

/// `grid` (G³, flat `(ix * G + iy) * G + iz`) grown by `reach` cells along each axis (a cube
/// of side 2 reach + 1 around every set cell), one axis at a time.
fn dilate(grid: &[bool], g: usize, reach: usize) -> Vec<bool> {
    let mut cur = grid.to_vec();
    for stride in [g * g, g, 1] {
        let mut next = vec![false; cur.len()];
        for (i, slot) in next.iter_mut().enumerate() {
            let pos = (i / stride) % g;
            let lo = pos.saturating_sub(reach);
            let hi = (pos + reach).min(g - 1);
            let base = i - pos * stride;
            *slot = (lo..=hi).any(|p| cur[base + p * stride]);
        }
        cur = next;
    }
    cur
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(g: usize, hot: &[(usize, usize, usize)]) -> Occupancy {
        let mut bound = vec![-100.0f32; g * g * g];
        for &(x, y, z) in hot {
            bound[(x * g + y) * g + z] = 10.0;
        }
        Occupancy { resolution: g, bound }
    }

    #[test]
    fn bricks_cover_the_occupied_cells_and_one_interval_around_them() {
        let g = 8;
        let occ = grid(g, &[(4, 4, 4)]);
        // Intervals of 1.5 cells (box 1, G 8: cell 0.125): reach 2 cells.
        let spec = BakeSpec { subdivisions: 2, fine_subdivisions: 0, epsilon: 1e-6, max_delta: 0.1875 };
        let layout = BrickLayout::new(&occ, &spec, 1.0).unwrap();
        assert_eq!(layout.brick_cells.len(), 5 * 5 * 5);
        for x in 0..g {
            for y in 0..g {
                for z in 0..g {
                    let near = [x, y, z].iter().all(|&c| (2..=6).contains(&c));
                    let b = layout.index[(x * g + y) * g + z];
                    assert_eq!(b != EMPTY, near, "{x} {y} {z}");
                    if b != EMPTY {
                        assert_eq!(layout.brick_cells[b as usize] as usize, (x * g + y) * g + z);
                    }
                }
            }
        }
    }

    #[test]
    fn a_fine_occupancy_grid_is_baked_in_blocks_of_its_cells() {
        assert_eq!([64, 32, 16, 48, 96, 128].map(baked_cells), [32, 32, 16, 48, 32, 32]);
        let occ = grid(64, &[(10, 20, 30)]);
        let spec = BakeSpec { subdivisions: 2, fine_subdivisions: 0, epsilon: 1e-6, max_delta: 0.02 };
        let layout = BrickLayout::new(&occ, &spec, 1.0).unwrap();
        // Block (5, 10, 15) of 32³, and one block around it (cells 1/32 wide > 0.02).
        assert_eq!((layout.cells, layout.brick_cells.len()), (32, 27));
        assert_ne!(layout.index[(5 * 32 + 10) * 32 + 15], EMPTY);
        assert_eq!(layout.index[(7 * 32 + 10) * 32 + 15], EMPTY);
    }

    #[test]
    fn an_empty_scene_has_no_bricks_and_bad_subdivisions_are_refused() {
        let occ = grid(4, &[]);
        let spec = BakeSpec { subdivisions: 4, fine_subdivisions: 0, epsilon: 1e-6, max_delta: 0.03 };
        assert!(BrickLayout::new(&occ, &spec, 1.0).unwrap().brick_cells.is_empty());
        let bad = BakeSpec { subdivisions: 9, ..spec };
        let e = BrickLayout::new(&occ, &bad, 1.0).unwrap_err().to_string();
        assert!(e.starts_with("baked_subdivisions:"), "{e}");
    }

    #[test]
    fn covers_needs_the_same_points_and_no_more_cells() {
        let a = BakeSpec { subdivisions: 4, fine_subdivisions: 0, epsilon: 1e-6, max_delta: 0.03 };
        assert!(a.covers(&a));
        assert!(a.covers(&BakeSpec { epsilon: 1e-4, max_delta: 0.02, ..a }));
        assert!(!a.covers(&BakeSpec { epsilon: 1e-7, ..a }));
        assert!(!a.covers(&BakeSpec { max_delta: 0.05, ..a }));
        assert!(!a.covers(&BakeSpec { subdivisions: 2, ..a }));
        assert!(!a.covers(&BakeSpec { fine_subdivisions: 8, ..a }));
    }

    #[test]
    fn a_two_level_layout_numbers_coarse_bricks_then_fine_ones() {
        let g = 8;
        let occ = grid(g, &[(1, 1, 1), (5, 5, 5)]);
        let spec = BakeSpec { subdivisions: 2, fine_subdivisions: 0, epsilon: 1e-6, max_delta: 0.1 };
        let one = BrickLayout::new(&occ, &spec, 1.0).unwrap();
        let n = one.brick_cells.len();
        assert!(n > 6);
        let is_fine: Vec<bool> = (0..n).map(|b| b % 3 == 0).collect();
        let two = one.two_level(&is_fine);
        let coarse: Vec<u32> = (0..n as u32).filter(|b| b % 3 != 0).collect();
        assert_eq!(two.coarse_bricks, coarse);
        let fine: Vec<u32> = (0..n).step_by(3).map(|b| one.brick_cells[b]).collect();
        assert_eq!(two.fine_cells, fine);
        for (b, &cell) in one.brick_cells.iter().enumerate() {
            let want = if b % 3 == 0 { coarse.len() + b / 3 } else { b - b / 3 - 1 };
            assert_eq!(two.index[cell as usize] as usize, want, "brick {b}");
        }
        assert_eq!(two.index.iter().filter(|&&b| b != EMPTY).count(), n);
    }

    #[test]
    fn the_colour_weight_is_the_lookups() {
        let source = crate::shaders::BAKED.source;
        for (name, value) in [("BAKED_COLOUR_FLOOR", COLOUR_FLOOR), ("BAKED_COLOUR_RAMP", COLOUR_RAMP)] {
            let line = source.lines().find(|l| l.starts_with(&format!("const {name}: f32 = "))).unwrap();
            let wgsl: f32 = line.rsplit(' ').next().unwrap().trim_end_matches(';').parse().unwrap();
            assert_eq!(wgsl, value, "{name}");
        }
    }

    #[test]
    fn a_brick_is_fine_where_a_surface_crosses_it_or_its_colour_turns_under_one() {
        let grey = |sigma: f32| [sigma, 0.5 * colour_weight(sigma), 0.5 * colour_weight(sigma), 0.0];
        let red = |sigma: f32| [sigma, 0.9 * colour_weight(sigma), 0.5 * colour_weight(sigma), 0.0];
        assert!(needs_fine([grey(-5.0), grey(20.0)]));
        assert!(needs_fine([grey(0.0), grey(60.0)]));
        assert!(!needs_fine([grey(-5.0), grey(9.0)])); // faint
        assert!(!needs_fine([grey(60.0), grey(80.0)])); // under a surface, one colour
        assert!(needs_fine([grey(60.0), red(80.0)])); // under a surface, a colour edge
        assert!(!needs_fine([grey(250.0), red(300.0)])); // deep inside: hidden
        assert!(!needs_fine([red(-5.0), grey(9.0)])); // the colour of faint points does not count
    }
}
