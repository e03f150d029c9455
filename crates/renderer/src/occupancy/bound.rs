//! The interval arithmetic of a bake: per cell, an upper bound on the raw density over every point
//! a sample in it can read (`docs/occupancy.md`). Its parent, `occupancy.rs`, runs it over a grid.

use crate::triplane::{Triplane, HIDDEN, N_CHANNELS, PLANE_AXES};

/// Widening of each cell, in plane coordinates, so that a sample whose float32 cell index
/// rounds into a neighbour still has its bilinear taps inside that neighbour's footprint
/// (float32 rounding of q is ~1e-6 inside the box; a cell at G = 64 is 3e-2 wide).
pub(super) const CELL_MARGIN: f64 = 1e-4;
/// Relative allowance for the float32 evaluation of the decoder in the kernel (dot products of
/// length <= 65, softplus and WGSL's exp/log precision): a few 1e-6 of the magnitudes involved.
pub(super) const F32_ALLOWANCE: f64 = 1e-5;

/// Per plane and 2-D cell of a `g`-cell grid: the centre and radius of each hidden unit's
/// pre-activation contribution over the cell's feature box (min/max of every channel over the
/// texels a sample in the cell can touch), laid out (3, g·g, HIDDEN).
pub(super) fn hidden_intervals(tri: &Triplane, g: usize) -> (Vec<f64>, Vec<f64>) {
    let d = &tri.decoder;
    // Per plane and 2-D cell: the hidden pre-activation's centre and radius contribution,
    // Σ_c w0[j,c] · centre_c and Σ_c |w0[j,c]| · radius_c, for the plane's feature box.
    let (h, w) = (tri.height, tri.width);
    let mut centre = vec![0f64; 3 * g * g * HIDDEN];
    let mut radius = vec![0f64; 3 * g * g * HIDDEN];
    let xs = footprints(g, w);
    let ys = footprints(g, h);
    let mut lo = vec![0f64; g * g * N_CHANNELS];
    let mut hi = vec![0f64; g * g * N_CHANNELS];
    let mut row_lo = vec![0f64; h * g];
    let mut row_hi = vec![0f64; h * g];
    for p in 0..3 {
        for c in 0..N_CHANNELS {
            let plane = &tri.planes[(p * N_CHANNELS + c) * h * w..][..h * w];
            // Separable min/max: over each cell's column range, then its row range.
            for y in 0..h {
                let row = &plane[y * w..][..w];
                for (a, fp) in xs.iter().enumerate() {
                    let (mut mn, mut mx) = (f64::INFINITY, f64::NEG_INFINITY);
                    for &v in &row[fp.first..=fp.last] {
                        mn = mn.min(v as f64);
                        mx = mx.max(v as f64);
                    }
                    row_lo[y * g + a] = mn;
                    row_hi[y * g + a] = mx;
                }
            }
            for (b, fy) in ys.iter().enumerate() {
                for (a, fx) in xs.iter().enumerate() {
                    let (mut mn, mut mx) = (f64::INFINITY, f64::NEG_INFINITY);
                    for y in fy.first..=fy.last {
                        mn = mn.min(row_lo[y * g + a]);
                        mx = mx.max(row_hi[y * g + a]);
                    }
                    // Zeros padding: a tap outside the plane contributes 0.
                    if fx.padded || fy.padded {
                        mn = mn.min(0.0);
                        mx = mx.max(0.0);
                    }
                    // 2-D cell index: (u cell a, v cell b).
                    lo[(a * g + b) * N_CHANNELS + c] = mn;
                    hi[(a * g + b) * N_CHANNELS + c] = mx;
                }
            }
        }
        for cell in 0..g * g {
            let (l, u) = (&lo[cell * N_CHANNELS..][..N_CHANNELS], &hi[cell * N_CHANNELS..][..N_CHANNELS]);
            for j in 0..HIDDEN {
                let wj = &d.w0[j * N_CHANNELS..][..N_CHANNELS];
                let (mut cs, mut rs) = (0f64, 0f64);
                for c in 0..N_CHANNELS {
                    let wv = wj[c] as f64;
                    cs += wv * 0.5 * (l[c] + u[c]);
                    rs += wv.abs() * 0.5 * (u[c] - l[c]);
                }
                centre[(p * g * g + cell) * HIDDEN + j] = cs;
                radius[(p * g * g + cell) * HIDDEN + j] = rs;
            }
        }
    }
    (centre, radius)
}

/// Upper bound on the raw density over 3-D cell `ijk` (interval arithmetic, `docs/occupancy.md`).
pub(super) fn cell_bound(
    d: &crate::triplane::Decoder,
    g: usize,
    ijk: [usize; 3],
    centre: &[f64],
    radius: &[f64],
    first_mag: &[f64],
) -> f64 {
    let offsets: [usize; 3] =
        std::array::from_fn(|p| ((p * g + ijk[PLANE_AXES[p][0]]) * g + ijk[PLANE_AXES[p][1]]) * HIDDEN);
    let mut upper = d.b1[0] as f64;
    let mut magnitude = (d.b1[0] as f64).abs();
    for j in 0..HIDDEN {
        let w1 = d.w1[j] as f64;
        if w1 == 0.0 {
            continue; // hand-built decoders use few hidden units for density
        }
        // Mean of the three planes' features: centre and radius average too. `e` widens the
        // pre-activation by the kernel's float32 error on it.
        let c =
            (centre[offsets[0] + j] + centre[offsets[1] + j] + centre[offsets[2] + j]) / 3.0 + d.b0[j] as f64;
        let r = (radius[offsets[0] + j] + radius[offsets[1] + j] + radius[offsets[2] + j]) / 3.0;
        let e = F32_ALLOWANCE * first_mag[j];
        // softplus is increasing: the hidden unit's end that maximises w1 · h, with the
        // kernel's relative softplus error.
        let h = if w1 >= 0.0 {
            softplus(c + r + e) * (1.0 + F32_ALLOWANCE)
        } else {
            softplus(c - r - e) * (1.0 - F32_ALLOWANCE)
        };
        upper += w1 * h;
        // softplus(x) <= max(x, 0) + ln 2 bounds |h| without a second exp.
        magnitude += w1.abs() * ((c + r + e).max(0.0) + std::f64::consts::LN_2);
    }
    // The second layer's float32 dot product.
    upper + F32_ALLOWANCE * magnitude
}

pub(super) fn softplus(x: f64) -> f64 {
    if x > 30.0 {
        x
    } else {
        x.exp().ln_1p()
    }
}

/// The smallest float32 >= `v` (finite inputs; huge values saturate to f32::MAX).
pub(super) fn round_up(v: f64) -> f32 {
    let f = (v as f32).clamp(f32::MIN, f32::MAX);
    if (f as f64) < v && f < f32::MAX {
        // The next float32 up (f32::next_up needs Rust 1.86; the MSRV is 1.85).
        match f {
            0.0 => f32::from_bits(1),
            _ if f > 0.0 => f32::from_bits(f.to_bits() + 1),
            _ => f32::from_bits(f.to_bits() - 1),
        }
    } else {
        f
    }
}

/// Texels one axis of a 2-D cell can reach through bilinear taps.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Footprint {
    pub(super) first: usize,
    pub(super) last: usize,
    /// A tap can fall outside the plane (zeros padding), so 0 is a possible value.
    pub(super) padded: bool,
}

/// For each of `g` cells along an axis of `n` texels: grid_sample(align_corners=False) maps
/// coordinate u to ix = ((u + 1) n - 1) / 2 and reads texels floor(ix) and floor(ix) + 1.
/// The outermost cells extend to infinity (points outside the box clamp to them).
pub(super) fn footprints(g: usize, n: usize) -> Vec<Footprint> {
    let ix = |u: f64| ((u + 1.0) * n as f64 - 1.0) * 0.5;
    (0..g)
        .map(|a| {
            let u0 = -1.0 + 2.0 * a as f64 / g as f64 - CELL_MARGIN;
            let u1 = -1.0 + 2.0 * (a + 1) as f64 / g as f64 + CELL_MARGIN;
            let first = if a == 0 { -1 } else { ix(u0).floor() as i64 };
            let last = if a + 1 == g { n as i64 } else { ix(u1).floor() as i64 + 1 };
            let padded = first < 0 || last > n as i64 - 1;
            let clamp = |v: i64| v.clamp(0, n as i64 - 1) as usize;
            Footprint { first: clamp(first), last: clamp(last), padded }
        })
        .collect()
}
