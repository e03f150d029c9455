//! The occupancy grid: a per-cell upper bound on the raw density, baked once per triplane on
//! the CPU, that lets the kernel skip the triplane fetch and decode of samples in empty space.
//! The bound and why it is conservative are in `docs/occupancy.md`.
//!
//! Cells are uniform in the plane coordinates q = 2 x / box_warp, G per axis over [-1, 1], and
//! the outermost cells also stand for everything beyond (the kernel clamps the cell index), so
//! every point in space has a cell whose bound holds. Grid layout: `bound[(ix * G + iy) * G + iz]`.

use crate::error::{Error, Result};
pub use crate::occupancy_grid::{Occupancy, DEFAULT_RESOLUTION, MAX_RESOLUTION};
use crate::triplane::{Triplane, HIDDEN, N_CHANNELS, PLANE_AXES};

/// Widening of each cell, in plane coordinates, so that a sample whose float32 cell index
/// rounds into a neighbour still has its bilinear taps inside that neighbour's footprint
/// (float32 rounding of q is ~1e-6 inside the box; a cell at G = 64 is 3e-2 wide).
const CELL_MARGIN: f64 = 1e-4;
/// Relative allowance for the float32 evaluation of the decoder in the kernel (dot products of
/// length <= 65, softplus and WGSL's exp/log precision): a few 1e-6 of the magnitudes involved.
const F32_ALLOWANCE: f64 = 1e-5;

impl Occupancy {
    /// CRC-32 of the planes (float32 values, `(3, 32, H, W)` order, little-endian) and the
    /// decoder (w0, b0, w1, b1 as float32): stored beside the grid in the `.npz` so a grid
    /// baked for other planes or weights is detected on load ([`Triplane::occupancy_checksum`]).
    pub fn checksum(tri: &Triplane) -> u32 {
        tri.occupancy_checksum()
    }

    /// Bakes the grid for `tri` with `resolution` cells per axis (see `docs/occupancy.md`).
    pub fn bake(tri: &Triplane, resolution: usize) -> Result<Occupancy> {
        tri.validate()?;
        let g = resolution;
        if !(1..=MAX_RESOLUTION).contains(&g) {
            return Err(Error::invalid(
                "resolution",
                format!("occupancy grid resolution must be in [1, {MAX_RESOLUTION}], got {g}"),
            ));
        }
        let d = &tri.decoder;
        let (centre, radius) = hidden_intervals(tri, g);
        // Magnitude of the first layer's terms, |b0_j| + Σ_c |w0[j,c]| · max |plane value|,
        // which bounds its float32 error (times F32_ALLOWANCE).
        let fmax = tri.planes.iter().fold(0f64, |m, &v| m.max((v as f64).abs()));
        let first_mag: Vec<f64> = (0..HIDDEN)
            .map(|j| {
                (d.b0[j] as f64).abs()
                    + fmax
                        * d.w0[j * N_CHANNELS..][..N_CHANNELS].iter().map(|&v| (v as f64).abs()).sum::<f64>()
            })
            .collect();

        let mut bound = vec![0f32; g * g * g];
        let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1).min(g);
        let per = g.div_ceil(threads);
        std::thread::scope(|s| {
            for (t, out) in bound.chunks_mut(per * g * g).enumerate() {
                let (centre, radius, first_mag) = (&centre, &radius, &first_mag);
                s.spawn(move || {
                    for (i, slot) in out.iter_mut().enumerate() {
                        let cell = t * per * g * g + i;
                        let ijk = [cell / (g * g), (cell / g) % g, cell % g];
                        *slot = round_up(cell_bound(d, g, ijk, centre, radius, first_mag));
                    }
                });
            }
        });
        Ok(Occupancy { resolution: g, bound })
    }
}

/// Per plane and 2-D cell of a `g`-cell grid: the centre and radius of each hidden unit's
/// pre-activation contribution over the cell's feature box (min/max of every channel over the
/// texels a sample in the cell can touch), laid out (3, g·g, HIDDEN).
fn hidden_intervals(tri: &Triplane, g: usize) -> (Vec<f64>, Vec<f64>) {
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
fn cell_bound(
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

fn softplus(x: f64) -> f64 {
    if x > 30.0 {
        x
    } else {
        x.exp().ln_1p()
    }
}

/// The smallest float32 >= `v` (finite inputs; huge values saturate to f32::MAX).
fn round_up(v: f64) -> f32 {
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
struct Footprint {
    first: usize,
    last: usize,
    /// A tap can fall outside the plane (zeros padding), so 0 is a possible value.
    padded: bool,
}

/// For each of `g` cells along an axis of `n` texels: grid_sample(align_corners=False) maps
/// coordinate u to ix = ((u + 1) n - 1) / 2 and reads texels floor(ix) and floor(ix) + 1.
/// The outermost cells extend to infinity (points outside the box clamp to them).
fn footprints(g: usize, n: usize) -> Vec<Footprint> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::triplane::{Decoder, PlaneDtype, SceneBounds, N_OUT};

    /// A tiny deterministic PRNG (no dependency) for test data.
    struct Lcg(u64);
    impl Lcg {
        fn next(&mut self) -> f32 {
            self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((self.0 >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        }
    }

    /// Smooth blobs in the planes and a decoder whose density follows channel 0.
    fn scene(size: usize, seed: u64) -> Triplane {
        let mut rng = Lcg(seed);
        let mut planes = vec![0f32; 3 * N_CHANNELS * size * size];
        for p in 0..3 {
            for c in 0..N_CHANNELS {
                let (cx, cy, s) = (rng.next() * 0.5, rng.next() * 0.5, 0.2 + 0.2 * rng.next().abs());
                for y in 0..size {
                    for x in 0..size {
                        let u = (2.0 * x as f32 + 1.0) / size as f32 - 1.0;
                        let v = (2.0 * y as f32 + 1.0) / size as f32 - 1.0;
                        let r2 = ((u - cx).powi(2) + (v - cy).powi(2)) / (s * s);
                        planes[((p * N_CHANNELS + c) * size + y) * size + x] =
                            1.5 * (-r2).exp() + 0.05 * rng.next();
                    }
                }
            }
        }
        let w0: Vec<f32> = (0..HIDDEN * N_CHANNELS).map(|_| rng.next() * 0.5).collect();
        let b0: Vec<f32> = (0..HIDDEN).map(|_| rng.next()).collect();
        let mut w1: Vec<f32> = (0..N_OUT * HIDDEN).map(|_| rng.next() * 0.3).collect();
        w1[..HIDDEN].iter_mut().for_each(|v| *v *= 6.0);
        let mut b1: Vec<f32> = (0..N_OUT).map(|_| rng.next()).collect();
        b1[0] = -8.0;
        Triplane {
            planes,
            height: size,
            width: size,
            plane_dtype: PlaneDtype::F32,
            decoder: Decoder { w0, b0, w1, b1 },
            bounds: SceneBounds::default(),
            camera: None,
            occupancy: None,
            source: None,
        }
    }

    /// EG3D's lookup and decoder in float64 at plane coordinates q (the brute-force check).
    fn raw_density(tri: &Triplane, q: [f64; 3]) -> f64 {
        let (h, w) = (tri.height, tri.width);
        let mut f = [0f64; N_CHANNELS];
        for (p, axes) in PLANE_AXES.iter().enumerate() {
            let ix = ((q[axes[0]] + 1.0) * w as f64 - 1.0) * 0.5;
            let iy = ((q[axes[1]] + 1.0) * h as f64 - 1.0) * 0.5;
            let (x0, y0) = (ix.floor(), iy.floor());
            let (fx, fy) = (ix - x0, iy - y0);
            for (dx, dy, wt) in [
                (0, 0, (1.0 - fx) * (1.0 - fy)),
                (1, 0, fx * (1.0 - fy)),
                (0, 1, (1.0 - fx) * fy),
                (1, 1, fx * fy),
            ] {
                let (x, y) = (x0 as i64 + dx, y0 as i64 + dy);
                if x < 0 || y < 0 || x >= w as i64 || y >= h as i64 {
                    continue;
                }
                for (c, fc) in f.iter_mut().enumerate() {
                    *fc += wt * tri.planes[((p * N_CHANNELS + c) * h + y as usize) * w + x as usize] as f64;
                }
            }
        }
        let d = &tri.decoder;
        let mut out = d.b1[0] as f64;
        for j in 0..HIDDEN {
            let row = &d.w0[j * N_CHANNELS..][..N_CHANNELS];
            let pre = d.b0[j] as f64 + row.iter().zip(&f).map(|(&w, &fc)| w as f64 * fc / 3.0).sum::<f64>();
            out += d.w1[j] as f64 * softplus(pre);
        }
        out
    }

    #[test]
    fn bake_is_conservative_under_dense_sampling() {
        let tri = scene(24, 7);
        let g = 8;
        let occ = Occupancy::bake(&tri, g).unwrap();
        let mut rng = Lcg(3);
        for _ in 0..40_000 {
            // Inside the box and up to 0.5 beyond it (edge cells stand for the outside).
            let q = [rng.next() as f64 * 1.5, rng.next() as f64 * 1.5, rng.next() as f64 * 1.5];
            let idx = q.map(|v| (((v + 1.0) * 0.5 * g as f64).floor()).clamp(0.0, g as f64 - 1.0) as usize);
            let b = occ.bound[(idx[0] * g + idx[1]) * g + idx[2]] as f64;
            let s = raw_density(&tri, q);
            assert!(s <= b, "density {s} above the cell bound {b} at {q:?}");
        }
        // Cell corners and faces too, where the footprints meet.
        for i in 0..=g {
            for j in 0..=g {
                let q = [-1.0 + 2.0 * i as f64 / g as f64, -1.0 + 2.0 * j as f64 / g as f64, 0.013];
                let idx =
                    q.map(|v| (((v + 1.0) * 0.5 * g as f64).floor()).clamp(0.0, g as f64 - 1.0) as usize);
                assert!(raw_density(&tri, q) <= occ.bound[(idx[0] * g + idx[1]) * g + idx[2]] as f64);
            }
        }
    }

    #[test]
    fn empty_scene_bakes_empty_and_threshold_is_consistent() {
        let mut tri = scene(16, 1);
        tri.planes.iter_mut().for_each(|v| *v = 0.0);
        tri.decoder.w1[..HIDDEN].iter_mut().for_each(|v| *v = 0.0);
        tri.decoder.b1[0] = -20.0;
        let occ = Occupancy::bake(&tri, 4).unwrap();
        let thr = Occupancy::raw_threshold(1e-6, 0.03);
        assert!(occ.bound.iter().all(|&b| (b as f64) <= thr), "{:?} vs {thr}", &occ.bound[..4]);
        assert_eq!(occ.empty_fraction(thr), 1.0);
        assert!(occ.bits(thr).iter().all(|&b| b == 0));
        // softplus(thr - 1) * delta == epsilon.
        assert!(((thr - 1.0).exp().ln_1p() * 0.03 - 1e-6).abs() < 1e-15);
    }

    #[test]
    fn footprints_cover_bilinear_taps() {
        for (g, n) in [(4, 16), (8, 5), (64, 256), (3, 2)] {
            let fps = footprints(g, n);
            assert!(fps[0].padded && fps[g - 1].padded);
            for k in 0..=1000 {
                let u = -1.0 + 2.0 * k as f64 / 1000.0;
                let a = (((u + 1.0) * 0.5 * g as f64).floor() as usize).min(g - 1);
                let ix = ((u + 1.0) * n as f64 - 1.0) * 0.5;
                for x in [ix.floor() as i64, ix.floor() as i64 + 1] {
                    let fp = fps[a];
                    if x < 0 || x >= n as i64 {
                        assert!(fp.padded);
                    } else {
                        assert!(fp.first as i64 <= x && x <= fp.last as i64, "g {g} n {n} u {u}");
                    }
                }
            }
        }
    }

    #[test]
    fn bake_time_256() {
        // Not a benchmark assertion: prints the bake time of a 256² triplane at G = 64.
        let tri = scene(256, 2);
        let start = std::time::Instant::now();
        let occ = Occupancy::bake(&tri, DEFAULT_RESOLUTION).unwrap();
        eprintln!(
            "occupancy bake 256² G=64: {:.1} ms, {:.1}% empty at eps 1e-6",
            start.elapsed().as_secs_f64() * 1e3,
            100.0 * occ.empty_fraction(Occupancy::raw_threshold(1e-6, 1.05 / 47.0))
        );
        assert_eq!(occ.bound.len(), 64 * 64 * 64);
    }
}
