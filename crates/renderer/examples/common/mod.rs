//! The scene the kernel-timing examples share, so their numbers compare: a 256² random triplane
//! with an EG3D-scaled decoder (a fixed xorshift stream, the same every run).

use lp3d_renderer::{Decoder, PlaneDtype, Triplane};

/// The random benchmark triplane of `frame_time` and `compile_time`.
pub fn random_triplane() -> Triplane {
    let mut state = 7u32;
    let mut rand = move || {
        state ^= state << 13;
        state ^= state >> 17;
        state ^= state << 5;
        (state as f32 / u32::MAX as f32) * 2.0 - 1.0
    };
    let size = 256;
    Triplane {
        planes: (0..3 * 32 * size * size).map(|_| rand() * 1.7).collect(),
        height: size,
        width: size,
        plane_dtype: PlaneDtype::F32,
        decoder: Decoder {
            w0: (0..64 * 32).map(|_| rand() * 0.3).collect(),
            b0: (0..64).map(|_| rand() * 0.1).collect(),
            w1: (0..33 * 64).map(|_| rand() * 0.2).collect(),
            b1: (0..33).map(|_| rand() * 0.1).collect(),
        },
        box_warp: 1.0,
        ray_start: 2.25,
        ray_end: 3.3,
        camera: None,
        occupancy: None,
        source: None,
    }
}
