//! Splits a fresh process's first render into its parts: device, pipeline build, first
//! dispatch (lavapipe JIT-compiles a pipeline on first use) and warm renders.
//!
//!     MESA_SHADER_CACHE_DIR=$(mktemp -d) cargo run --release -p lp3d-renderer --example compile_time -- [R] [S] [N] [repeats] [dump.f32]
//!
//! Same random scene as `frame_time`. With a fifth argument the outputs (features, depth,
//! weights sum) of the last render are written there as raw float32, to compare kernel variants.

use std::time::Instant;

use lp3d_renderer::{GpuContext, Outputs, RenderSettings, Renderer};

mod common;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (settings, repeats) = common::settings_from_args(&args);
    let (r, s, n) = (settings.resolution, settings.depth_resolution, settings.depth_resolution_importance);
    let dump = args.get(4).cloned();
    let tri = common::random_triplane();
    let t0 = Instant::now();
    let ctx = GpuContext::headless().expect("GPU adapter");
    let t_ctx = t0.elapsed().as_secs_f64();
    let t = Instant::now();
    let renderer = Renderer::new(&ctx).expect("pipelines");
    let t_new = t.elapsed().as_secs_f64();
    let gpu = renderer.upload(&tri).expect("upload");
    let cams = common::frontal_camera();
    let t = Instant::now();
    let c = common::process_cpu_s();
    renderer.render(&gpu, &cams, &RenderSettings { resolution: 4, ..settings }, Outputs::ALL).expect("first");
    let t_first = t.elapsed().as_secs_f64();
    let c_first = common::process_cpu_s() - c;
    let mut times = Vec::new();
    let mut cpu = Vec::new();
    let mut last = None;
    for _ in 0..repeats {
        let t = Instant::now();
        let c = common::process_cpu_s();
        last = Some(renderer.render(&gpu, &cams, &settings, Outputs::ALL).expect("render"));
        times.push(t.elapsed().as_secs_f64() * 1e3);
        cpu.push((common::process_cpu_s() - c) * 1e3);
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
