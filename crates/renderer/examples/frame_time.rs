//! Times one render configuration on the headless device: a quick loop for kernel work.
//!
//!     cargo run --release -p lp3d-renderer --example frame_time -- [R] [S] [N] [repeats] [outputs]
//!
//! The scene is a 256² random triplane with an EG3D-scaled decoder, seen from the frontal camera.
//! The committed benchmarks are the Python scripts in bench/; this is for iterating on shaders.

use std::time::Instant;

use lp3d_renderer::camera::{FFHQ_FOCAL, FFHQ_RADIUS};
use lp3d_renderer::{Camera, GpuContext, Outputs, RenderSettings, Renderer};

mod common;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let arg = |i: usize, d: u32| args.get(i).map(|s| s.parse().expect("integer argument")).unwrap_or(d);
    let (r, s, n, repeats) = (arg(0, 128), arg(1, 48), arg(2, 48), arg(3, 3));
    let outputs = match args.get(4) {
        Some(list) => Outputs::from_names(&list.split(',').collect::<Vec<_>>()).expect("outputs"),
        None => Outputs::ALL,
    };
    let tri = common::random_triplane();
    let ctx = GpuContext::headless().expect("GPU adapter");
    let renderer = Renderer::new(&ctx).expect("pipelines");
    let gpu = renderer.upload(&tri).expect("upload");
    let half_pi = std::f64::consts::FRAC_PI_2;
    let cams = [Camera::look_at(half_pi, half_pi, FFHQ_RADIUS, [0.0, 0.0, 0.2], FFHQ_FOCAL)];
    let settings = RenderSettings {
        resolution: r,
        depth_resolution: s,
        depth_resolution_importance: n,
        ..Default::default()
    };
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
        let c = process_cpu_ms();
        let out = renderer.render(&gpu, &cams, &settings, outputs).expect("render");
        times.push(t.elapsed().as_secs_f64() * 1e3);
        cpu.push(process_cpu_ms() - c);
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

/// User + system CPU time of this process (all threads, lavapipe's workers included), in ms.
/// Less sensitive than wall time to other jobs sharing the cores.
fn process_cpu_ms() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let fields: Vec<&str> = stat.rsplit(')').next().unwrap_or("").split_whitespace().collect();
    let ticks: f64 = fields.get(11).and_then(|u| u.parse::<f64>().ok()).unwrap_or(0.0)
        + fields.get(12).and_then(|s| s.parse::<f64>().ok()).unwrap_or(0.0);
    ticks * 10.0 // USER_HZ is 100 on Linux
}
