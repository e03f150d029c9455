//! What the GPU tests share: a pseudo-random triplane from a fixed xorshift stream.

use lp3d_renderer::{Decoder, PlaneDtype, SceneBounds, Triplane};

/// An `h` × `w` float32 triplane whose plane values are uniform in ±`plane_scale` and whose
/// decoder has EG3D-like scales, drawn from the xorshift stream seeded with `seed` (planes
/// first, then w0, b0, w1, b1), so that each test's scene is the same every run.
pub fn random_triplane(seed: u32, h: usize, w: usize, plane_scale: f32, source: &str) -> Triplane {
    let mut state = seed;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 17;
        state ^= state << 5;
        (state as f32 / u32::MAX as f32) * 2.0 - 1.0
    };
    let planes = (0..3 * 32 * h * w).map(|_| next() * plane_scale).collect();
    Triplane {
        planes,
        height: h,
        width: w,
        plane_dtype: PlaneDtype::F32,
        decoder: Decoder {
            w0: (0..64 * 32).map(|_| next() * 0.3).collect(),
            b0: (0..64).map(|_| next() * 0.1).collect(),
            w1: (0..33 * 64).map(|_| next() * 0.2).collect(),
            b1: (0..33).map(|_| next() * 0.1).collect(),
        },
        bounds: SceneBounds::default(),
        camera: None,
        occupancy: None,
        source: Some(source.into()),
    }
}
