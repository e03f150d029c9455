//! Measures ways to evaluate samples other than exact mode's fetch + decode (issue 23, item 4),
//! on the headless device, before any of them is built into `render_rays`:
//!
//!     cargo run --release -p lp3d-renderer --example decode_variants -- [triplane.npz] [repeats]
//!
//! Each variant evaluates the same samples (128² rays × 16 depths in the box, neighbouring lanes
//! at neighbouring pixels, as in a render) and writes the raw density and the features:
//! - `exact`: `sample_triplane` + `decode`, the kernel's own code (shaders/triplane.wgsl,
//!   shaders/decoder.wgsl);
//! - `cooperative`: the same fetch; then the decoder's first layer as one matrix product over a
//!   workgroup's 64 samples (each invocation one hidden unit for all 64, weights in registers,
//!   features and hidden values in workgroup memory), the second layer per sample;
//! - `projected f32` / `projected f16`: the first layer folded into the planes. The decoder's
//!   first layer is linear and the fetch is a weighted sum, so W0 · mean(taps) = mean(taps of
//!   W0 · plane): the planes are stored as their 64 hidden pre-activations per texel and the
//!   fetch returns the hidden layer's input directly (float32: the same numbers up to rounding;
//!   float16: the bytes of today's float32 planes).
//!
//! Prints each variant's median process CPU ms per dispatch (alternated, `repeats` rounds) and its largest
//! difference from `exact` in raw density and in the features. The scene is the 256² random
//! triplane of `frame_time`, or the given file.

use std::time::Instant;

use lp3d_renderer::gpu_types::DecoderUniform;
use lp3d_renderer::{GpuContext, Triplane};
use wgpu::util::DeviceExt;

#[allow(dead_code)] // the scene of frame_time; not every helper is used here
mod common;

const RAYS: u32 = 128;
const STEPS: u32 = 16;
const HIDDEN: usize = 64;
const CHANNELS: usize = 32;

const PRELUDE: &str = r#"
struct Params { plane_h: u32, plane_w: u32, flags: u32, box_warp: f32, rays: u32, steps: u32, _p0: u32, _p1: u32 }
struct Decoder {
    w0: array<vec4<f32>, 512>,
    b0: array<vec4<f32>, 16>,
    w1: array<vec4<f32>, 528>,
    b1: array<vec4<f32>, 9>,
}
const FLAG_HALF_PLANES: u32 = 4u;
override N_FEAT: u32 = 32u;
override PROJ_HALF: bool = false;
@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> planes: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read> proj: array<vec4<u32>>;
@group(0) @binding(3) var<uniform> decoder: Decoder;
@group(0) @binding(4) var<storage, read_write> out: array<vec4<f32>>;

// Sample i: pixel i % rays², depth i / rays², in world units inside the box.
fn sample_pos(i: u32) -> vec3<f32> {
    let r = params.rays;
    let p = i % (r * r);
    let step = i / (r * r);
    let x = (f32(p % r) + 0.5) / f32(r);
    let y = (f32(p / r) + 0.5) / f32(r);
    let z = (f32(step) + 0.5) / f32(params.steps);
    return (vec3<f32>(x, y, z) * 1.6 - 0.8) * (params.box_warp * 0.5);
}

// Two vec4 per sample: (sigma_raw, features 0..2), then the sum of the other features (kept live).
fn write_out(i: u32, sigma_raw: f32, f: ptr<function, array<vec4<f32>, 8>>) {
    var rest = vec4<f32>(0.0);
    for (var q = 1u; q < 8u; q++) {
        rest += (*f)[q];
    }
    out[2u * i] = vec4<f32>(sigma_raw, (*f)[0].xyz);
    out[2u * i + 1u] = rest;
}

@compute @workgroup_size(64)
fn exact(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    var feat = array<vec4<f32>, 8>();
    var cur = array<vec4<f32>, 8>();
    sample_triplane(sample_pos(i), &feat);
    let sigma_raw = decode(N_FEAT, &feat, &cur);
    write_out(i, sigma_raw, &cur);
}

// --- projected planes: 64 hidden pre-activations per texel ---
fn add_proj_tap(p: u32, x: i32, y: i32, w: f32, h: ptr<function, array<vec4<f32>, 16>>) {
    if (x < 0 || y < 0 || x >= i32(params.plane_w) || y >= i32(params.plane_h)) {
        return;
    }
    let texel = (p * params.plane_h + u32(y)) * params.plane_w + u32(x);
    if (PROJ_HALF) {
        let base = texel * 8u;
        for (var q = 0u; q < 8u; q++) {
            let v = proj[base + q];
            (*h)[2u * q] += w * vec4<f32>(halves_to_f32(v.x), halves_to_f32(v.y));
            (*h)[2u * q + 1u] += w * vec4<f32>(halves_to_f32(v.z), halves_to_f32(v.w));
        }
    } else {
        let base = texel * 16u;
        for (var q = 0u; q < 16u; q++) {
            (*h)[q] += w * bitcast<vec4<f32>>(proj[base + q]);
        }
    }
}

fn add_proj_plane(p: u32, u: f32, v: f32, h: ptr<function, array<vec4<f32>, 16>>) {
    let ix = ((u + 1.0) * f32(params.plane_w) - 1.0) * 0.5;
    let iy = ((v + 1.0) * f32(params.plane_h) - 1.0) * 0.5;
    if (!(ix > -1.0 && iy > -1.0 && ix < f32(params.plane_w) && iy < f32(params.plane_h))) {
        return;
    }
    let x0 = floor(ix);
    let y0 = floor(iy);
    let fx = ix - x0;
    let fy = iy - y0;
    for (var c = 0u; c < 4u; c++) {
        let dx = c & 1u;
        let dy = c >> 1u;
        let w = select(1.0 - fx, fx, dx == 1u) * select(1.0 - fy, fy, dy == 1u);
        add_proj_tap(p, i32(x0) + i32(dx), i32(y0) + i32(dy), w, h);
    }
}

fn softplus4(x: vec4<f32>) -> vec4<f32> {
    return vec4<f32>(softplus(x.x), softplus(x.y), softplus(x.z), softplus(x.w));
}

@compute @workgroup_size(64)
fn projected(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    let q = plane_coords(sample_pos(i));
    var h = array<vec4<f32>, 16>();
    for (var p = 0u; p < 3u; p++) {
        let uv = select(select(q.zx, q.xz, p == 1u), q.xy, p == 0u);
        add_proj_plane(p, uv.x, uv.y, &h);
    }
    for (var j = 0u; j < 16u; j++) {
        h[j] = softplus4(h[j] / 3.0 + decoder.b0[j]);
    }
    var cur = array<vec4<f32>, 8>();
    let sigma_raw = layer2(&h, &cur);
    write_out(i, sigma_raw, &cur);
}

// --- cooperative: the first layer as a matrix product over the workgroup ---
var<workgroup> wg_feat: array<array<vec4<f32>, 8>, 64>;
var<workgroup> wg_hidden: array<f32, 4096>;

@compute @workgroup_size(64)
fn cooperative(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let i = gid.x;
    var feat = array<vec4<f32>, 8>();
    sample_triplane(sample_pos(i), &feat);
    wg_feat[lid] = feat;
    workgroupBarrier();
    // This invocation is hidden unit `lid` for all 64 samples.
    let r = 8u * lid;
    let w0 = decoder.w0[r];
    let w1 = decoder.w0[r + 1u];
    let w2 = decoder.w0[r + 2u];
    let w3 = decoder.w0[r + 3u];
    let w4 = decoder.w0[r + 4u];
    let w5 = decoder.w0[r + 5u];
    let w6 = decoder.w0[r + 6u];
    let w7 = decoder.w0[r + 7u];
    let b = decoder.b0[lid / 4u][lid % 4u];
    for (var s = 0u; s < 64u; s++) {
        let x = dot(w0, wg_feat[s][0]) + dot(w1, wg_feat[s][1]) + dot(w2, wg_feat[s][2]) + dot(w3, wg_feat[s][3])
            + dot(w4, wg_feat[s][4]) + dot(w5, wg_feat[s][5]) + dot(w6, wg_feat[s][6]) + dot(w7, wg_feat[s][7]) + b;
        wg_hidden[s * 64u + lid] = softplus(x);
    }
    workgroupBarrier();
    var h = array<vec4<f32>, 16>();
    for (var j = 0u; j < 16u; j++) {
        let o = lid * 64u + 4u * j;
        h[j] = vec4<f32>(wg_hidden[o], wg_hidden[o + 1u], wg_hidden[o + 2u], wg_hidden[o + 3u]);
    }
    var cur = array<vec4<f32>, 8>();
    let sigma_raw = layer2(&h, &cur);
    write_out(i, sigma_raw, &cur);
}
"#;

/// The decoder's second layer with constant indices (as scripts/gen_decoder_wgsl.py writes it):
/// the raw density returned, features 0..N_FEAT through the clamped sigmoid into `dst`.
fn layer2_source() -> String {
    let row = |o: usize| {
        let terms: Vec<String> =
            (0..16).map(|j| format!("dot(decoder.w1[{}u], (*h)[{j}u])", 16 * o + j)).collect();
        format!("{} + decoder.b1[{}u][{}u]", terms.join(" + "), o / 4, o % 4)
    };
    let mut s = String::from(
        "fn layer2(h: ptr<function, array<vec4<f32>, 16>>, dst: ptr<function, array<vec4<f32>, 8>>) -> f32 {\n",
    );
    for q in 0..8 {
        let cond = if q == 0 { "N_FEAT > 0u" } else { "N_FEAT == 32u" };
        let comps: Vec<String> = (0..4).map(|c| format!("clamped_sigmoid({})", row(1 + 4 * q + c))).collect();
        s +=
            &format!("    if ({cond}) {{\n        (*dst)[{q}u] = vec4<f32>({});\n    }}\n", comps.join(", "));
    }
    s += &format!("    return {};\n}}\n", row(0));
    s
}

fn buffer(dev: &wgpu::Device, label: &str, bytes: &[u8], usage: wgpu::BufferUsages) -> wgpu::Buffer {
    dev.create_buffer_init(&wgpu::util::BufferInitDescriptor { label: Some(label), contents: bytes, usage })
}

/// Hidden pre-activations of each texel, W0 · plane, channel-last (3, H, W, 64), in float64.
fn projected_planes(tri: &Triplane) -> Vec<f64> {
    let planes = tri.planes_channel_last();
    let w0 = &tri.decoder.w0;
    let texels = planes.len() / CHANNELS;
    let mut out = vec![0f64; texels * HIDDEN];
    for t in 0..texels {
        let f = &planes[t * CHANNELS..][..CHANNELS];
        for j in 0..HIDDEN {
            out[t * HIDDEN + j] = (0..CHANNELS).map(|c| w0[j * CHANNELS + c] as f64 * f[c] as f64).sum();
        }
    }
    out
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let tri = match args.first().filter(|a| a.ends_with(".npz")) {
        Some(path) => Triplane::load(path).expect("triplane file"),
        None => common::random_triplane(),
    };
    let repeats: usize = args.iter().find_map(|a| a.parse().ok()).unwrap_or(5);
    let ctx = GpuContext::headless().expect("GPU adapter");
    let dev = &ctx.device;

    let source = format!(
        "{PRELUDE}\n{}\n{}\n{}",
        include_str!("../shaders/triplane.wgsl"),
        include_str!("../shaders/decoder.wgsl"),
        layer2_source()
    );
    let module = dev.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("decode variants"),
        source: wgpu::ShaderSource::Wgsl(source.into()),
    });

    let n = (RAYS * RAYS * STEPS) as u64;
    let planes32: Vec<u32> = tri.planes_channel_last().iter().map(|v| v.to_bits()).collect();
    let proj = projected_planes(&tri);
    let proj32: Vec<u32> = proj.iter().map(|&v| (v as f32).to_bits()).collect();
    let proj16: Vec<u32> = proj
        .chunks(2)
        .map(|p| {
            half::f16::from_f64(p[0]).to_bits() as u32 | (half::f16::from_f64(p[1]).to_bits() as u32) << 16
        })
        .collect();
    let params: [u32; 8] =
        [tri.height as u32, tri.width as u32, 0, tri.bounds.box_warp.to_bits(), RAYS, STEPS, 0, 0];
    let storage = wgpu::BufferUsages::STORAGE;
    let params_buf = buffer(dev, "params", bytemuck::cast_slice(&params), wgpu::BufferUsages::UNIFORM);
    let decoder = DecoderUniform::from_decoder(&tri.decoder);
    let decoder_buf = buffer(dev, "decoder", bytemuck::bytes_of(&decoder), wgpu::BufferUsages::UNIFORM);
    let planes_buf = buffer(dev, "planes", bytemuck::cast_slice(&planes32), storage);
    let proj32_buf = buffer(dev, "projected f32", bytemuck::cast_slice(&proj32), storage);
    let proj16_buf = buffer(dev, "projected f16", bytemuck::cast_slice(&proj16), storage);
    let out_bytes = n * 32;
    let out_buf = dev.create_buffer(&wgpu::BufferDescriptor {
        label: Some("out"),
        size: out_bytes,
        usage: storage | wgpu::BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    });
    let read_buf = dev.create_buffer(&wgpu::BufferDescriptor {
        label: Some("read"),
        size: out_bytes,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });

    // (name, entry point, features decoded, float16 projected planes)
    let mut variants = Vec::new();
    for n_feat in [3.0, 32.0] {
        variants.push(("exact", "exact", n_feat, false));
        variants.push(("cooperative", "cooperative", n_feat, false));
        variants.push(("projected f32", "projected", n_feat, false));
        variants.push(("projected f16", "projected", n_feat, true));
    }
    let bench =
        Bench { ctx: &ctx, out: &out_buf, read: &read_buf, bytes: out_bytes, groups: (n / 64) as u32 };
    let mut pipelines = Vec::new();
    for &(name, entry, n_feat, half) in &variants {
        let t = Instant::now();
        let pipeline = dev.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(name),
            layout: None,
            module: &module,
            entry_point: Some(entry),
            compilation_options: wgpu::PipelineCompilationOptions {
                constants: &[("N_FEAT", n_feat), ("PROJ_HALF", if half { 1.0 } else { 0.0 })],
                ..Default::default()
            },
            cache: None,
        });
        let layout = pipeline.get_bind_group_layout(0);
        let mut entries = vec![
            wgpu::BindGroupEntry { binding: 0, resource: params_buf.as_entire_binding() },
            wgpu::BindGroupEntry { binding: 3, resource: decoder_buf.as_entire_binding() },
            wgpu::BindGroupEntry { binding: 4, resource: out_buf.as_entire_binding() },
        ];
        if entry != "projected" {
            entries.push(wgpu::BindGroupEntry { binding: 1, resource: planes_buf.as_entire_binding() });
        } else {
            let p = if half { &proj16_buf } else { &proj32_buf };
            entries.push(wgpu::BindGroupEntry { binding: 2, resource: p.as_entire_binding() });
        }
        let group = dev.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &layout,
            entries: &entries,
        });
        let (_, values) = bench.dispatch(&pipeline, &group, true); // compiles, and the outputs to compare
        eprintln!("{name} ({n_feat} features): first dispatch {:.1} s", t.elapsed().as_secs_f64());
        pipelines.push((pipeline, group, values.expect("outputs")));
    }

    let mut times: Vec<Vec<f64>> = vec![Vec::new(); variants.len()];
    for _ in 0..repeats {
        for (k, (pipeline, group, _)) in pipelines.iter().enumerate() {
            times[k].push(bench.dispatch(pipeline, group, false).0);
        }
    }
    println!(
        "adapter {} | {} samples ({RAYS}² rays × {STEPS}) | planes {}² | {repeats} alternated rounds",
        ctx.adapter_info.name, n, tri.width
    );
    println!("| variant | features | CPU ms per dispatch (median) | vs exact | max |Δ sigma_raw| | max |Δ features| |");
    println!("|---|---|---|---|---|---|");
    for (k, &(name, _, n_feat, _)) in variants.iter().enumerate() {
        let base = k - k % 4; // the `exact` variant of the same feature count
        let med = median(&mut times[k]);
        let base_med = median(&mut times[base].clone());
        let (ds, df) = max_diff(&pipelines[k].2, &pipelines[base].2, n_feat as usize);
        println!("| {name} | {n_feat} | {med:.1} | {:.2}× | {ds:.2e} | {df:.2e} |", base_med / med);
    }
}

/// One dispatch over all samples: its process CPU ms (lavapipe's threads included, less sensitive
/// to other jobs than wall time), and its outputs when `read` (copied after the timed part).
struct Bench<'a> {
    ctx: &'a GpuContext,
    out: &'a wgpu::Buffer,
    read: &'a wgpu::Buffer,
    bytes: u64,
    groups: u32,
}

impl Bench<'_> {
    fn dispatch(
        &self,
        pipeline: &wgpu::ComputePipeline,
        group: &wgpu::BindGroup,
        read: bool,
    ) -> (f64, Option<Vec<f32>>) {
        let dev = &self.ctx.device;
        let c = common::process_cpu_s();
        let mut enc = dev.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, group, &[]);
            pass.dispatch_workgroups(self.groups, 1, 1);
        }
        if read {
            enc.copy_buffer_to_buffer(self.out, 0, self.read, 0, self.bytes);
        }
        self.ctx.queue.submit([enc.finish()]);
        dev.poll(wgpu::PollType::wait_indefinitely()).expect("poll");
        let ms = (common::process_cpu_s() - c) * 1e3;
        if !read {
            return (ms, None);
        }
        self.read.map_async(wgpu::MapMode::Read, .., |r| r.expect("map"));
        dev.poll(wgpu::PollType::wait_indefinitely()).expect("poll");
        let values = {
            let view = self.read.get_mapped_range(0..self.bytes).expect("mapped range");
            bytemuck::cast_slice::<u8, f32>(&view).to_vec()
        };
        self.read.unmap();
        (ms, Some(values))
    }
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Largest differences in raw density and in features (the first three, plus the sum of the
/// rest when all are decoded).
fn max_diff(a: &[f32], b: &[f32], n_feat: usize) -> (f64, f64) {
    let (mut ds, mut df) = (0f64, 0f64);
    for (x, y) in a.chunks(8).zip(b.chunks(8)) {
        ds = ds.max((x[0] - y[0]).abs() as f64);
        let last = if n_feat == 32 { 8 } else { 4 };
        for c in 1..last {
            df = df.max((x[c] - y[c]).abs() as f64);
        }
    }
    (ds, df)
}
