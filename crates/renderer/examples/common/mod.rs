//! The scene the kernel-timing examples share, so their numbers compare: a 256² random triplane
//! with an EG3D-scaled decoder (a fixed xorshift stream, the same every run), its camera and the
//! settings from the command line.

#[path = "../../tests/common/mod.rs"]
mod random;

use lp3d_renderer::camera::{FFHQ_FOCAL, FFHQ_RADIUS};
use lp3d_renderer::{Camera, RenderSettings, Triplane};

/// The random benchmark triplane of `frame_time` and `compile_time`: the tests' generator
/// (`tests/common`), 256², planes in ±1.7.
pub fn random_triplane() -> Triplane {
    Triplane { source: None, ..random::random_triplane(7, 256, 256, 1.7, "") }
}

/// The frontal FFHQ camera the examples render the scene from.
pub fn frontal_camera() -> [Camera; 1] {
    let half_pi = std::f64::consts::FRAC_PI_2;
    [Camera::lookat_pose(half_pi, half_pi, FFHQ_RADIUS, [0.0, 0.0, 0.2], FFHQ_FOCAL)]
}

/// The examples' `[R] [S] [N] [repeats]` arguments (defaults 128, 48, 48, 3) and the settings
/// they give: R² rays, S coarse + N fine samples.
pub fn settings_from_args(args: &[String]) -> (RenderSettings, u32) {
    let arg = |i: usize, d: u32| args.get(i).map(|s| s.parse().expect("integer argument")).unwrap_or(d);
    let settings = RenderSettings {
        resolution: arg(0, 128),
        depth_resolution: arg(1, 48),
        depth_resolution_importance: arg(2, 48),
        ..Default::default()
    };
    (settings, arg(3, 3))
}

/// User + system CPU time of this process (all threads, lavapipe's workers included), in
/// seconds: less sensitive than wall time to other jobs sharing the cores.
pub fn process_cpu_s() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let fields: Vec<&str> = stat.rsplit(')').next().unwrap_or("").split_whitespace().collect();
    let ticks: f64 = fields.get(11).and_then(|u| u.parse::<f64>().ok()).unwrap_or(0.0)
        + fields.get(12).and_then(|s| s.parse::<f64>().ok()).unwrap_or(0.0);
    ticks / 100.0 // USER_HZ is 100 on Linux
}
