//! The occupancy grid as data: cells, bounds, their checks and the bits the kernel reads. A
//! triplane holds one; baking it from a triplane is `crate::occupancy` (`docs/occupancy.md`).

use crate::error::{Error, Result};

/// Default cells per axis.
pub const DEFAULT_RESOLUTION: usize = 64;
/// Largest accepted cells per axis.
pub const MAX_RESOLUTION: usize = 512;
/// A baked grid: an upper bound on the decoder's raw density (`sigma_raw`, before EG3D's
/// `softplus(x - 1)`) over each cell, float32 rounded up.
#[derive(Debug, Clone, PartialEq)]
pub struct Occupancy {
    /// Cells per axis, G.
    pub resolution: usize,
    /// G³ bounds, `(ix * G + iy) * G + iz`.
    pub bound: Vec<f32>,
}

impl Occupancy {
    pub fn validate(&self) -> Result<()> {
        let g = self.resolution;
        if !(1..=MAX_RESOLUTION).contains(&g) {
            return Err(Error::invalid(
                "occupancy",
                format!("grid must be (G, G, G) with G in [1, {MAX_RESOLUTION}], got G = {g}"),
            ));
        }
        if self.bound.len() != g * g * g {
            return Err(Error::invalid("occupancy", "data length does not match (G, G, G)"));
        }
        if let Some(i) = self.bound.iter().position(|x| !x.is_finite()) {
            return Err(Error::invalid("occupancy", format!("contains NaN/Inf at flat index {i}")));
        }
        Ok(())
    }

    /// The raw-density threshold below which a cell is empty for a per-interval opacity bound
    /// `epsilon` and intervals at most `max_delta` long: softplus(r - 1) · max_delta = epsilon.
    pub fn raw_threshold(epsilon: f64, max_delta: f64) -> f64 {
        // softplus⁻¹(y) = ln(expm1(y)), accurate for tiny y in float64.
        1.0 + (epsilon / max_delta).exp_m1().ln()
    }

    /// One bit per cell, set where the cell may hold density above `raw_threshold`.
    pub fn bits(&self, raw_threshold: f64) -> Vec<u32> {
        let mut bits = vec![0u32; self.bound.len().div_ceil(32).max(1)];
        for (i, &b) in self.bound.iter().enumerate() {
            let empty = (b as f64) <= raw_threshold; // NaN is never empty
            if !empty {
                bits[i / 32] |= 1 << (i % 32);
            }
        }
        bits
    }

    /// Fraction of cells empty at `raw_threshold`.
    pub fn empty_fraction(&self, raw_threshold: f64) -> f64 {
        let empty = self.bound.iter().filter(|&&b| b as f64 <= raw_threshold).count();
        empty as f64 / self.bound.len() as f64
    }
}
