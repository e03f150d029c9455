//! Splits a fresh process's first render into its parts: device, pipeline build, first
//! dispatch (lavapipe JIT-compiles a pipeline on first use) and warm renders.
//!
//!     MESA_SHADER_CACHE_DIR=$(mktemp -d) cargo run --release -p lp3d-renderer --example compile_time -- [R] [S] [N] [repeats] [dump.f32]
//!
//! Same random scene as `frame_time`. With a fifth argument the outputs (features, depth,
//! weights sum) of the last render are written there as raw float32, to compare kernel variants.

use std::time::Instant;

use lp3d_renderer::camera::{FFHQ_FOCAL, FFHQ_RADIUS};
use lp3d_renderer::{Camera, GpuContext, Outputs, RenderSettings, Renderer};

mod common;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let arg = |i: usize, d: u32| args.get(i).map(|s| s.parse().expect("integer argument")).unwrap_or(d);
    let (r, s, n, repeats) = (arg(0, 128), arg(1, 48), arg(2, 48), arg(3, 3));
    let dump = args.get(4).cloned();
    let tri = common::random_triplane();
    let t0 = Instant::now();
    let ctx = GpuContext::headless().expect("GPU adapter");
    let t_ctx = t0.elapsed().as_secs_f64();
    let t = Instant::now();
    let renderer = Renderer::new(&ctx).expect("pipelines");
    let t_new = t.elapsed().as_secs_f64();
    let gpu = renderer.upload(&tri).expect("upload");
    let half_pi = std::f64::consts::FRAC_PI_2;
    let cams = [Camera::look_at(half_pi, half_pi, FFHQ_RADIUS, [0.0, 0.0, 0.2], FFHQ_FOCAL)];
    let settings = RenderSettings {
        resolution: r,
        depth_resolution: s,
        depth_resolution_importance: n,
        ..Default::default()
    };
    let t = Instant::now();
    let c = process_cpu_s();
    renderer.render(&gpu, &cams, &RenderSettings { resolution: 4, ..settings }, Outputs::ALL).expect("first");
    let t_first = t.elapsed().as_secs_f64();
    let c_first = process_cpu_s() - c;
    let mut times = Vec::new();
    let mut cpu = Vec::new();
    let mut last = None;
    for _ in 0..repeats {
        let t = Instant::now();
        let c = process_cpu_s();
        last = Some(renderer.render(&gpu, &cams, &settings, Outputs::ALL).expect("render"));
        times.push(t.elapsed().as_secs_f64() * 1e3);
        cpu.push((process_cpu_s() - c) * 1e3);
        eprintln!(
            "  render at {:.1} s: {:.0} ms, kernel {:?}",
            t0.elapsed().as_secs_f64(),
            times[times.len() - 1],
            renderer.kernel()
        );
    }
    times.sort_by(f64::total_cmp);
    cpu.sort_by(f64::total_cmp);
    let out = last.expect("repeats >= 1");
    let wsum: f64 = out.weights_sum.as_ref().map(|w| w.iter().map(|&v| v as f64).sum()).unwrap_or(0.0);
    println!(
        "device {t_ctx:.2} s | Renderer::new {t_new:.2} s | first 4² render {t_first:.2} s (CPU {c_first:.2} s) | \
         R={r} S+N={s}+{n}: median {:.1} ms (min {:.1}, CPU {:.0} ms) | weights_sum total {wsum:.6}",
        times[times.len() / 2],
        times[0],
        cpu[cpu.len() / 2]
    );
    if let Some(path) = dump {
        let mut v: Vec<f32> = Vec::new();
        for part in [&out.features, &out.depth, &out.weights_sum].into_iter().flatten() {
            v.extend_from_slice(part);
        }
        std::fs::write(path, bytemuck::cast_slice(&v)).expect("write dump");
    }
}

/// User + system CPU time of this process (all threads), in seconds: less sensitive than wall
/// time to other jobs sharing the cores (the JIT compile is one thread).
fn process_cpu_s() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let fields: Vec<&str> = stat.rsplit(')').next().unwrap_or("").split_whitespace().collect();
    let ticks: f64 = fields.get(11).and_then(|u| u.parse::<f64>().ok()).unwrap_or(0.0)
        + fields.get(12).and_then(|s| s.parse::<f64>().ok()).unwrap_or(0.0);
    ticks / 100.0 // USER_HZ is 100 on Linux
}
