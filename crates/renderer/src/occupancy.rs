//! The occupancy grid: a per-cell upper bound on the raw density, baked once per triplane on
//! the CPU, that lets the kernel skip the triplane fetch and decode of samples in empty space.
//! The bound and why it is conservative are in `docs/occupancy.md`.
//!
//! Cells are uniform in the plane coordinates q = 2 x / box_warp, G per axis over [-1, 1], and
//! the outermost cells also stand for everything beyond (the kernel clamps the cell index), so
//! every point in space has a cell whose bound holds. Grid layout: `bound[(ix * G + iy) * G + iz]`.
//! The grid as data (what a triplane holds, its checks, the kernel's bits) is `triplane/occupancy.rs`;
//! the bound of one cell is `occupancy/bound.rs`.

mod bound;

pub use crate::triplane::occupancy::{Occupancy, DEFAULT_RESOLUTION, MAX_RESOLUTION};

use bound::{cell_bound, hidden_intervals, round_up};

use crate::error::{Error, Result};
use crate::triplane::{Triplane, HIDDEN, N_CHANNELS};

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

#[cfg(test)]
mod tests {
    use super::bound::{footprints, softplus};
    use super::*;
    use crate::triplane::{Decoder, PlaneDtype, SceneBounds, N_OUT, PLANE_AXES};

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
