//! Times one render configuration on the headless device: a quick loop for kernel work.
//!
//!     cargo run --release -p lp3d-renderer --example frame_time -- [R] [S] [N] [repeats] [outputs]
//!
//! The scene is a 256² random triplane with an EG3D-scaled decoder, seen from the frontal camera.
//! The committed benchmarks are the Python scripts in bench/; this is for iterating on shaders.

use std::time::Instant;

use lp3d_renderer::{GpuContext, Outputs, RenderSettings, Renderer};

mod common;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (settings, repeats) = common::settings_from_args(&args);
    let (r, s, n) = (settings.resolution, settings.depth_resolution, settings.depth_resolution_importance);
    let outputs = match args.get(4) {
        Some(list) => Outputs::from_names(&list.split(',').collect::<Vec<_>>()).expect("outputs"),
        None => Outputs::ALL,
    };
    let tri = common::random_triplane();
    let ctx = GpuContext::headless().expect("GPU adapter");
    let renderer = Renderer::new(&ctx).expect("pipelines");
    let gpu = renderer.upload(&tri).expect("upload");
    let cams = common::frontal_camera();
    let t0 = Instant::now();
    renderer.render(&gpu, &cams, &RenderSettings { resolution: 4, ..settings }, outputs).expect("warm-up");
    eprintln!(
        "adapter: {} | warm-up (pipeline compile) {:.1} s",
        ctx.adapter_info.name,
        t0.elapsed().as_secs_f64()
    );
    let mut times = Vec::new();
    let mut cpu = Vec::new();
    let mut checksum = 0.0f64;
    for _ in 0..repeats {
        let t = Instant::now();
        let c = common::process_cpu_s();
        let out = renderer.render(&gpu, &cams, &settings, outputs).expect("render");
        times.push(t.elapsed().as_secs_f64() * 1e3);
        cpu.push((common::process_cpu_s() - c) * 1e3);
        checksum = out.weights_sum.map(|w| w.iter().map(|&v| v as f64).sum()).unwrap_or(0.0);
    }
    times.sort_by(f64::total_cmp);
    cpu.sort_by(f64::total_cmp);
    println!(
        "R={r} S+N={s}+{n} outputs={outputs:?}: median {:.1} ms/frame (min {:.1}), process CPU {:.0} ms/frame | weights_sum total {checksum:.4}",
        times[times.len() / 2],
        times[0],
        cpu[cpu.len() / 2]
    );
}
