//! The super-resolution kernels against a float64 CPU reference that follows torch's ops one by
//! one (`FoldedSuperResolution.forward`: transposed convolution, pad, FIR, bias, lrelu, ...), for
//! the student's shape and EG3D's widths; batching; and the checks on weights and features.

use std::sync::{Arc, OnceLock};

use lp3d_renderer::superres::{SrLayer, SuperRes, SuperresBlock, SuperresKernels, SuperresWeights};
use lp3d_renderer::{shaders, Error, GpuContext};

fn gpu() -> &'static (GpuContext, Arc<SuperresKernels>) {
    static GPU: OnceLock<(GpuContext, Arc<SuperresKernels>)> = OnceLock::new();
    GPU.get_or_init(|| {
        let ctx = GpuContext::headless().expect("a GPU adapter (lavapipe in CI)");
        let kernels = Arc::new(SuperresKernels::new(&ctx.device).expect("superres pipelines"));
        (ctx, kernels)
    })
}

/// Uniform in ±1 from a xorshift stream.
struct Stream(u32);
impl Stream {
    fn next(&mut self) -> f32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 17;
        self.0 ^= self.0 << 5;
        (self.0 as f32 / u32::MAX as f32) * 2.0 - 1.0
    }
    fn vec(&mut self, n: usize, scale: f32) -> Vec<f32> {
        (0..n).map(|_| self.next() * scale).collect()
    }
}

/// Random weights of a demodulated network's scale (each output's weights of unit norm).
fn random_weights(
    seed: u32,
    in_channels: usize,
    input_resolution: usize,
    widths: &[usize],
) -> SuperresWeights {
    let mut s = Stream(seed);
    let mut cin = in_channels;
    let blocks = widths
        .iter()
        .map(|&c| {
            let up = (3.0 / (cin * 9) as f32).sqrt();
            let conv = (3.0 / (c * 9) as f32).sqrt();
            let b = SuperresBlock {
                channels: c,
                conv_up: s.vec(c * cin * 9, up),
                bias_up: s.vec(c, 0.1),
                conv: s.vec(c * c * 9, conv),
                bias: s.vec(c, 0.1),
                rgb_weight: s.vec(3 * c, (1.0 / c as f32).sqrt()),
                rgb_bias: s.vec(3, 0.1),
            };
            cin = c;
            b
        })
        .collect();
    SuperresWeights { in_channels, input_resolution, blocks }
}

/// A (c, h, w) float64 image.
struct Img {
    c: usize,
    h: usize,
    w: usize,
    v: Vec<f64>,
}
impl Img {
    fn zeros(c: usize, h: usize, w: usize) -> Img {
        Img { c, h, w, v: vec![0.0; c * h * w] }
    }
    fn at(&self, c: usize, y: usize, x: usize) -> f64 {
        self.v[(c * self.h + y) * self.w + x]
    }
    fn set(&mut self, c: usize, y: usize, x: usize, v: f64) {
        let i = (c * self.h + y) * self.w + x;
        self.v[i] = v;
    }
    /// Zero padding of `p0` before and `p1` after on both axes.
    fn pad(&self, p0: usize, p1: usize) -> Img {
        let mut out = Img::zeros(self.c, self.h + p0 + p1, self.w + p0 + p1);
        for c in 0..self.c {
            for y in 0..self.h {
                for x in 0..self.w {
                    out.set(c, y + p0, x + p0, self.at(c, y, x));
                }
            }
        }
        out
    }
    /// The 4x4 FIR filter [1,3,3,1] ⊗ [1,3,3,1] / 64 with gain 4, valid convolution.
    fn fir(&self) -> Img {
        let t = [1.0, 3.0, 3.0, 1.0];
        let mut out = Img::zeros(self.c, self.h - 3, self.w - 3);
        for c in 0..self.c {
            for y in 0..out.h {
                for x in 0..out.w {
                    let mut acc = 0.0;
                    for a in 0..4 {
                        for b in 0..4 {
                            acc += t[a] * t[b] / 16.0 * self.at(c, y + a, x + b);
                        }
                    }
                    out.set(c, y, x, acc);
                }
            }
        }
        out
    }
    fn bias_lrelu(&mut self, bias: &[f32]) {
        let n = self.h * self.w;
        for (i, v) in self.v.iter_mut().enumerate() {
            let x = *v + bias[i / n] as f64;
            *v = if x >= 0.0 { x } else { 0.2 * x } * 2f64.sqrt();
        }
    }
}

/// The folded network in float64, one image.
fn reference(w: &SuperresWeights, features: &[f32]) -> Vec<f64> {
    let r0 = w.input_resolution;
    let mut x = Img { c: w.in_channels, h: r0, w: r0, v: features.iter().map(|&v| v as f64).collect() };
    let mut img = Img { c: 3, h: r0, w: r0, v: x.v[..3 * r0 * r0].to_vec() };
    for b in &w.blocks {
        let (c, cin, r) = (b.channels, x.c, x.h);
        // conv_transpose2d, stride 2: y[o, 2i + ky, 2j + kx] += x[ci, i, j] W[o, ci, ky, kx].
        let mut y = Img::zeros(c, 2 * r + 1, 2 * r + 1);
        for o in 0..c {
            for ci in 0..cin {
                for i in 0..r {
                    for j in 0..r {
                        let v = x.at(ci, i, j);
                        for ky in 0..3 {
                            for kx in 0..3 {
                                let wv = b.conv_up[((o * cin + ci) * 3 + ky) * 3 + kx] as f64;
                                let (yy, xx) = (2 * i + ky, 2 * j + kx);
                                y.set(o, yy, xx, y.at(o, yy, xx) + v * wv);
                            }
                        }
                    }
                }
            }
        }
        let mut x1 = y.pad(1, 1).fir();
        x1.bias_lrelu(&b.bias_up);
        let n = 2 * r;
        let p = x1.pad(1, 1);
        let mut x2 = Img::zeros(c, n, n);
        for o in 0..c {
            for yy in 0..n {
                for xx in 0..n {
                    let mut acc = 0.0;
                    for ci in 0..c {
                        for ky in 0..3 {
                            for kx in 0..3 {
                                acc += b.conv[((o * c + ci) * 3 + ky) * 3 + kx] as f64
                                    * p.at(ci, yy + ky, xx + kx);
                            }
                        }
                    }
                    x2.set(o, yy, xx, acc);
                }
            }
        }
        x2.bias_lrelu(&b.bias);
        // The image: zeros inserted, pad (2, 1), FIR; plus ToRGB.
        let mut z = Img::zeros(3, n, n);
        for ch in 0..3 {
            for i in 0..r {
                for j in 0..r {
                    z.set(ch, 2 * i, 2 * j, img.at(ch, i, j));
                }
            }
        }
        let mut up = z.pad(2, 1).fir();
        for ch in 0..3 {
            for yy in 0..n {
                for xx in 0..n {
                    let mut acc = b.rgb_bias[ch] as f64;
                    for ci in 0..c {
                        acc += b.rgb_weight[ch * c + ci] as f64 * x2.at(ci, yy, xx);
                    }
                    up.set(ch, yy, xx, up.at(ch, yy, xx) + acc);
                }
            }
        }
        img = up;
        x = x2;
    }
    img.v
}

fn max_abs(a: &[f32], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(&x, &y)| (x as f64 - y).abs()).fold(0.0, f64::max)
}

fn check_parity(weights: &SuperresWeights, n_images: usize, seed: u32) -> f64 {
    let (ctx, kernels) = gpu();
    let sr = SuperRes::new(ctx, kernels.clone(), weights).unwrap();
    let per = weights.in_channels * weights.input_resolution.pow(2);
    let features = Stream(seed).vec(n_images * per, 1.0);
    let got = sr.apply(&features, n_images).unwrap();
    let ro = weights.output_resolution();
    assert_eq!(got.len(), n_images * 3 * ro * ro);
    let mut worst = 0.0f64;
    for i in 0..n_images {
        let want = reference(weights, &features[i * per..(i + 1) * per]);
        worst = worst.max(max_abs(&got[i * 3 * ro * ro..(i + 1) * 3 * ro * ro], &want));
    }
    eprintln!(
        "superres parity: widths {:?}, max abs {worst:.3e}",
        weights.blocks.iter().map(|b| b.channels).collect::<Vec<_>>()
    );
    worst
}

#[test]
fn matches_the_reference_for_the_students_shape_batched() {
    // Two ×2 blocks from 32 channels, widths that are not whole groups of 8.
    let w = random_weights(7, 32, 8, &[12, 6]);
    let err = check_parity(&w, 3, 11);
    assert!(err <= 1e-4, "max abs {err}");
}

#[test]
fn matches_the_reference_at_eg3ds_widths() {
    // EG3D's SuperresolutionHybrid8XDC widths (32 -> 256 -> 128), a small input to keep the float64
    // reference quick; the kernels read every size from their uniforms.
    let w = random_weights(3, 32, 6, &[256, 128]);
    let err = check_parity(&w, 1, 5);
    assert!(err <= 1e-3, "max abs {err}");
}

#[test]
fn the_transposed_convolution_runs_in_chunks_when_it_is_the_largest_activation() {
    // Width 20 from 8²: its transposed convolution's output (17² per channel) is larger than every
    // block's input and output, so it runs in chunks of 16 + 4 channels.
    let w = random_weights(8, 4, 8, &[20, 4]);
    let err = check_parity(&w, 2, 6);
    assert!(err <= 1e-4, "max abs {err}");
}

#[test]
fn one_block_and_few_channels() {
    let w = random_weights(9, 3, 5, &[1]);
    let err = check_parity(&w, 2, 2);
    assert!(err <= 1e-5, "max abs {err}");
}

#[test]
fn a_batch_equals_its_images_one_by_one() {
    let (ctx, kernels) = gpu();
    let w = random_weights(1, 32, 8, &[16, 8]);
    let sr = SuperRes::new(ctx, kernels.clone(), &w).unwrap();
    let per = 32 * 64;
    let features = Stream(4).vec(4 * per, 1.0);
    let all = sr.apply(&features, 4).unwrap();
    let out = 3 * 32 * 32;
    for i in 0..4 {
        let one = sr.apply(&features[i * per..(i + 1) * per], 1).unwrap();
        assert_eq!(one, all[i * out..(i + 1) * out], "image {i}");
    }
}

#[test]
fn bad_weights_and_features_name_the_field() {
    let (ctx, kernels) = gpu();
    let good = random_weights(2, 32, 8, &[8, 4]);
    let refuse = |w: &SuperresWeights| match SuperRes::new(ctx, kernels.clone(), w) {
        Err(Error::InvalidInput { field, message }) => format!("{field}: {message}"),
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("accepted"),
    };
    let mut w = good.clone();
    w.blocks[1].conv.pop();
    assert!(refuse(&w).starts_with("convs[1]: expected shape [4, 4, 3, 3]"), "{}", refuse(&w));
    let mut w = good.clone();
    w.blocks[0].rgb_bias[2] = f32::NAN;
    assert_eq!(refuse(&w), "rgb_biases[0]: contains NaN/Inf at flat index 2");
    let mut w = good.clone();
    w.blocks[1].channels = 5;
    assert!(refuse(&w).starts_with("convs_up[1]: expected shape [5, 8, 3, 3]"), "{}", refuse(&w));
    let mut w = good.clone();
    w.in_channels = 2;
    assert!(refuse(&w).starts_with("in_channels:"), "{}", refuse(&w));
    let mut w = good.clone();
    w.input_resolution = 512;
    assert!(refuse(&w).starts_with("input_resolution:"), "{}", refuse(&w));
    let mut w = good.clone();
    w.blocks.clear();
    assert!(refuse(&w).starts_with("blocks:"), "{}", refuse(&w));

    let sr = SuperRes::new(ctx, kernels.clone(), &good).unwrap();
    let e = sr.apply(&[0.0; 10], 1).unwrap_err().to_string();
    assert!(e.starts_with("features: expected (1, 32, 8, 8)"), "{e}");
    let mut f = vec![0.0; 32 * 64];
    f[5] = f32::INFINITY;
    assert_eq!(sr.apply(&f, 1).unwrap_err().to_string(), "features: contains NaN/Inf at flat index 5");
    // Weights that overflow float32 on the way are reported, not returned as Inf.
    let mut w = good.clone();
    w.blocks[0].conv_up.iter_mut().for_each(|v| *v = 3e38);
    let sr = SuperRes::new(ctx, kernels.clone(), &w).unwrap();
    let e = sr.apply(&vec![1.0; 32 * 64], 1).unwrap_err().to_string();
    assert!(e.starts_with("superres: the network overflowed float32"), "{e}");
}

/// `lp3d share`'s page compiles every stage file as one module (`shader_sources`): the render
/// module's and the super-resolution module's side by side must validate together.
#[test]
fn the_render_and_superres_files_make_one_module() {
    let source = format!("{}\n{}", shaders::render_module_source(), shaders::superres_module_source());
    let module = naga::front::wgsl::parse_str(&source).expect("WGSL parses");
    naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::default())
        .validate(&module)
        .expect("WGSL validates");
}

#[test]
fn the_layer_uniform_matches_the_wgsl() {
    let module = naga::front::wgsl::parse_str(&shaders::superres_module_source()).expect("WGSL parses");
    naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::default())
        .validate(&module)
        .expect("WGSL validates");
    let mut layouter = naga::proc::Layouter::default();
    layouter.update(module.to_ctx()).unwrap();
    let (handle, _) = module.types.iter().find(|(_, t)| t.name.as_deref() == Some("SrLayer")).unwrap();
    assert_eq!(layouter[handle].size as usize, std::mem::size_of::<SrLayer>());
    let names: Vec<&str> = module.entry_points.iter().map(|e| e.name.as_str()).collect();
    let listed: Vec<&str> = shaders::SUPERRES_ENTRY_POINTS.iter().map(|e| e.name).collect();
    assert_eq!(names, listed);
}

/// Seconds per image at the student's shape (64² -> 256², widths 64 and 32); run with
/// `--ignored --nocapture`. bench/superres_speed.py measures it and EG3D's shape through Python,
/// beside onnxruntime.
#[test]
#[ignore]
fn time_per_image() {
    let (ctx, kernels) = gpu();
    eprintln!("binding limit {} bytes", ctx.limits.max_storage_buffer_binding_size);
    let r = 64;
    let w = random_weights(1, 32, r, &[64, 32]);
    let sr = SuperRes::new(ctx, kernels.clone(), &w).unwrap();
    let features = Stream(3).vec(32 * r * r, 1.0);
    sr.apply(&features, 1).unwrap();
    let t = std::time::Instant::now();
    sr.apply(&features, 1).unwrap();
    eprintln!("{r}² -> {}²: {:.3} s per image", w.output_resolution(), t.elapsed().as_secs_f64());
}
