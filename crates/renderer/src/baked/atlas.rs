//! Where a two-level field's fine bricks live on the GPU: a 3D texture (rgba16float, one texel
//! per point: sigma_raw, w r, w g, w b), the bricks side by side in it. A storage buffer binding
//! is capped (128 MiB on lavapipe), and the fine bricks that reach exact 48+48's error (k_f = 16)
//! take more (docs/performance.md, "Bake time and size"); a texture is limited only by its extent.
//!
//! Fine brick f sits at brick slot `(f % bx, (f / bx) % by, f / (bx by))` of the texture's
//! `bx × by × bz` slots of `(k_f + 1)³` texels; its point (a, b, c) is texel `slot (k_f + 1) +
//! (c, b, a)`, so that a texture row holds the `c` run the field's values store contiguously.
//! The lookup does no division to find a slot: on the GPU a fine brick's cell holds its slot in
//! the index ([`FineAtlas::index_word`]), where the CPU's index holds its brick number.

use crate::baked::EMPTY;
use crate::error::{Error, Result};

/// The flag of a fine brick's GPU index word (`BAKED_FINE` in `shaders/baked.wgsl`); below it the
/// slot, 10 bits per axis (x, y, z from the top), so at most [`MAX_SLOTS`] per axis.
pub const FINE_FLAG: u32 = 1 << 31;
/// Slots per axis that [`FineAtlas::index_word`] can name.
pub const MAX_SLOTS: u32 = 1 << 10;

/// The fine bricks' texture: its slots per axis and texels per brick edge.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FineAtlas {
    /// Points per brick edge, k_f + 1.
    pub k1: u32,
    /// Brick slots along the texture's x, y and z.
    pub slots: [u32; 3],
}

impl FineAtlas {
    /// The smallest-depth atlas of `n_bricks` fine bricks of `k_f + 1` points per edge in a 3D
    /// texture at most `max_extent` texels on a side (error naming `baked_fine_subdivisions`
    /// when they do not fit).
    pub fn new(n_bricks: usize, fine_subdivisions: u32, max_extent: u32) -> Result<FineAtlas> {
        let k1 = fine_subdivisions + 1;
        let per_axis = (max_extent / k1).clamp(1, MAX_SLOTS) as usize;
        let n = n_bricks.max(1);
        let bx = per_axis.min(n);
        let by = per_axis.min(n.div_ceil(bx));
        let bz = n.div_ceil(bx * by);
        if k1 > max_extent || bz > per_axis {
            return Err(Error::invalid(
                "baked_fine_subdivisions",
                format!(
                    "{n_bricks} fine bricks of {k1}³ points do not fit a 3D texture of {max_extent}³ texels: \
                     use fewer fine subdivisions or a larger occupancy_epsilon"
                ),
            ));
        }
        Ok(FineAtlas { k1, slots: [bx as u32, by as u32, bz as u32] })
    }

    /// The texture's extent in texels (x, y, z).
    pub fn extent(&self) -> [u32; 3] {
        self.slots.map(|s| s * self.k1)
    }

    /// The slot of fine brick `f`: x, then y, then z.
    pub fn slot(&self, f: usize) -> [usize; 3] {
        let [bx, by, _] = self.slots.map(|s| s as usize);
        [f % bx, f / bx % by, f / (bx * by)]
    }

    /// The first texel of fine brick `f`.
    pub fn origin(&self, f: usize) -> [usize; 3] {
        self.slot(f).map(|s| s * self.k1 as usize)
    }

    /// The GPU's index word of fine brick `f`: [`FINE_FLAG`] and its slot.
    pub fn index_word(&self, f: usize) -> u32 {
        let [x, y, z] = self.slot(f).map(|s| s as u32);
        FINE_FLAG | x << 20 | y << 10 | z
    }

    /// The index as the GPU reads it: the CPU's `index` with each fine brick's number (`fine_first`
    /// and above) replaced by its [`FineAtlas::index_word`].
    pub fn gpu_index(&self, index: &[u32], fine_first: u32) -> Vec<u32> {
        index
            .iter()
            .map(
                |&b| {
                    if b != EMPTY && b >= fine_first {
                        self.index_word((b - fine_first) as usize)
                    } else {
                        b
                    }
                },
            )
            .collect()
    }

    /// The texture's texels (four float16 each, rows `row_texels` long, x fastest) from the fine
    /// bricks' points as the field stores them (`fine_values`: 4 halves per point, brick after
    /// brick, point (a, b, c) at `(a (k_f+1) + b)(k_f+1) + c`). Unused slots are zeros.
    pub fn texels_from_bricks(&self, fine_values: &[u16], row_texels: usize) -> Vec<u16> {
        let [_, h, d] = self.extent().map(|e| e as usize);
        let k1 = self.k1 as usize;
        let mut out = vec![0u16; row_texels * h * d * 4];
        for (f, brick) in fine_values.chunks_exact(k1 * k1 * k1 * 4).enumerate() {
            let [x0, y0, z0] = self.origin(f);
            for (run, points) in brick.chunks_exact(k1 * 4).enumerate() {
                let (a, b) = (run / k1, run % k1);
                let at = (((z0 + a) * h + y0 + b) * row_texels + x0) * 4;
                out[at..at + k1 * 4].copy_from_slice(points);
            }
        }
        out
    }

    /// The inverse of [`FineAtlas::texels_from_bricks`]: the first `n_bricks` bricks' points.
    pub fn bricks_from_texels(&self, texels: &[u16], row_texels: usize, n_bricks: usize) -> Vec<u16> {
        let h = self.extent()[1] as usize;
        let k1 = self.k1 as usize;
        let mut out = Vec::with_capacity(n_bricks * k1 * k1 * k1 * 4);
        for f in 0..n_bricks {
            let [x0, y0, z0] = self.origin(f);
            for a in 0..k1 {
                for b in 0..k1 {
                    let at = (((z0 + a) * h + y0 + b) * row_texels + x0) * 4;
                    out.extend_from_slice(&texels[at..at + k1 * 4]);
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bricks_fill_x_then_y_then_z_and_refuse_what_does_not_fit() {
        let a = FineAtlas::new(10, 2, 9).unwrap(); // 3 slots per axis
        assert_eq!(a.slots, [3, 3, 2]);
        assert_eq!(a.extent(), [9, 9, 6]);
        assert_eq!([a.origin(0), a.origin(4), a.origin(9)], [[0, 0, 0], [3, 3, 0], [0, 0, 3]]);
        assert_eq!(FineAtlas::new(2, 2, 9).unwrap().slots, [2, 1, 1]);
        assert_eq!(FineAtlas::new(0, 16, 2048).unwrap().slots, [1, 1, 1]);
        let e = FineAtlas::new(28, 2, 9).unwrap_err().to_string();
        assert!(e.starts_with("baked_fine_subdivisions:"), "{e}");
    }

    #[test]
    fn a_fine_bricks_index_word_holds_its_slot_and_never_reads_as_empty() {
        let a = FineAtlas::new(10, 2, 9).unwrap();
        assert_eq!(a.index_word(4), FINE_FLAG | 1 << 20 | 1 << 10);
        assert_eq!(a.index_word(9), FINE_FLAG | 1);
        assert_eq!(
            a.gpu_index(&[EMPTY, 0, 3, 7], 3),
            vec![EMPTY, 0, FINE_FLAG, FINE_FLAG | 1 << 20 | 1 << 10]
        );
        let big = FineAtlas::new(2_000_000, 4, 1 << 16).unwrap(); // slots capped at 1024 per axis
        assert_eq!(big.slots[0], MAX_SLOTS);
        assert!((0..2_000_000).step_by(997).all(|f| big.index_word(f) != EMPTY));
    }

    #[test]
    fn texels_and_bricks_round_trip_with_points_where_the_shader_reads_them() {
        let a = FineAtlas::new(5, 2, 6).unwrap(); // 2 x 2 x 2 slots of 3³
        let n_halves = 5 * 27 * 4;
        let values: Vec<u16> = (0..n_halves as u16).collect();
        let row = 8; // padded rows, as a readback's
        let texels = a.texels_from_bricks(&values, row);
        assert_eq!(a.bricks_from_texels(&texels, row, 5), values);
        // Brick 3, point (a, b, c) = (2, 0, 1): texel origin (3, 3, 0) + (c, b, a).
        let h = a.extent()[1] as usize;
        let (x, y, z) = (3 + 1, 3, 2);
        let at = ((z * h + y) * row + x) * 4;
        let point = (2 * 3) * 3 + 1;
        assert_eq!(texels[at..at + 4], values[(3 * 27 + point) * 4..][..4]);
    }
}
