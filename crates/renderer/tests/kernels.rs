//! The two compiled forms of the render kernel (`shaders/decoder.wgsl`'s unrolled and rolled
//! decoders) give bit-identical outputs, so do the bake kernels built with them, and a renderer
//! that starts with the quick kernel and switches to the fast one after its background compile
//! changes no bit either.

mod common;

use lp3d_renderer::camera::{FFHQ_FOCAL, FFHQ_RADIUS};
use lp3d_renderer::kernel::{Kernel, KernelChoice};
use lp3d_renderer::{
    BakeSpec, Camera, GpuContext, GpuTriplane, Occupancy, Outputs, PlaneDtype, RenderSettings, Renderer,
    Triplane,
};

fn test_triplane(dtype: PlaneDtype) -> Triplane {
    let mut tri = common::random_triplane(2024, 12, 10, 1.5, "kernels test");
    if dtype == PlaneDtype::F16 {
        tri.planes = tri.planes.iter().map(|&v| half::f16::from_f32(v).to_f32()).collect();
        tri.plane_dtype = dtype;
    }
    tri
}

/// Every output of a few settings (exact, jittered over white, no importance pass; all
/// outputs and rgb alone), as float bits.
fn render_bits(renderer: &Renderer, gpu: &GpuTriplane) -> Vec<Vec<u32>> {
    let half_pi = std::f64::consts::FRAC_PI_2;
    let cams = [
        Camera::lookat_pose(half_pi, half_pi, FFHQ_RADIUS, [0.0, 0.0, 0.0], FFHQ_FOCAL),
        Camera::lookat_pose(half_pi + 0.4, half_pi - 0.2, FFHQ_RADIUS, [0.0, 0.0, 0.2], FFHQ_FOCAL),
    ];
    let exact = RenderSettings {
        resolution: 8,
        depth_resolution: 12,
        depth_resolution_importance: 12,
        ..Default::default()
    };
    let jittered = RenderSettings { deterministic: false, white_back: true, seed: 7, ..exact };
    let coarse_only = RenderSettings { depth_resolution_importance: 0, ..exact };
    let mut all = Vec::new();
    for settings in [exact, jittered, coarse_only] {
        for outputs in [Outputs::ALL, Outputs::from_names(&["rgb"]).unwrap()] {
            let out = renderer.render(gpu, &cams, &settings, outputs).unwrap();
            for part in [out.features, out.rgb, out.depth, out.weights_sum].into_iter().flatten() {
                all.push(part.iter().map(|v| v.to_bits()).collect());
            }
        }
    }
    all
}

fn assert_same(a: &[Vec<u32>], b: &[Vec<u32>], what: &str) {
    assert_eq!(a.len(), b.len());
    for (k, (x, y)) in a.iter().zip(b).enumerate() {
        let differ = x.iter().zip(y).filter(|(p, q)| p != q).count();
        assert_eq!(differ, 0, "{what}: output {k} differs in {differ} of {} values", x.len());
    }
}

#[test]
fn fast_and_quick_kernels_agree_bit_for_bit() {
    let ctx = GpuContext::headless().expect("a GPU adapter (lavapipe in CI)");
    let fast = Renderer::with_kernel(&ctx, KernelChoice::Fast).unwrap();
    let quick = Renderer::with_kernel(&ctx, KernelChoice::Quick).unwrap();
    assert_eq!(fast.kernel(), Kernel::Fast);
    assert_eq!(quick.kernel(), Kernel::Quick);
    for dtype in [PlaneDtype::F32, PlaneDtype::F16] {
        let tri = test_triplane(dtype);
        let a = render_bits(&fast, &fast.upload(&tri).unwrap());
        let b = render_bits(&quick, &quick.upload(&tri).unwrap());
        // Not vacuous: the scene has visible density.
        let wsum = &a[3];
        assert!(wsum.iter().any(|&w| f32::from_bits(w) > 0.05), "{dtype:?}: an empty render");
        assert_same(&a, &b, &format!("{dtype:?} planes, fast vs quick"));
    }
}

#[test]
fn quick_then_fast_switches_kernels_without_changing_a_bit() {
    let ctx = GpuContext::headless().expect("a GPU adapter (lavapipe in CI)");
    let renderer = Renderer::with_kernel(&ctx, KernelChoice::QuickThenFast).unwrap();
    let tri = test_triplane(PlaneDtype::F32);
    let gpu = renderer.upload(&tri).unwrap();
    assert_eq!(renderer.kernel(), Kernel::Quick);
    let before = render_bits(&renderer, &gpu);
    assert_eq!(renderer.wait_for_fast_kernel().unwrap(), Kernel::Fast);
    let after = render_bits(&renderer, &gpu);
    assert_eq!(renderer.kernel(), Kernel::Fast);
    assert_same(&before, &after, "before vs after the switch");
}

/// Both levels of a two-level field, as float16 bits: the bake with the fast kernel's unrolled
/// decoder (what a renderer bakes with once the fast kernel serves) and with the quick kernel's
/// rolled one.
#[test]
fn fast_and_quick_kernels_bake_the_same_field() {
    let ctx = GpuContext::headless().expect("a GPU adapter (lavapipe in CI)");
    let mut tri = test_triplane(PlaneDtype::F32);
    // The density row scaled up so that the raw density swings across the box: a surface crosses
    // some bricks and not others (checked below).
    tri.decoder.b1[0] = 0.0;
    for w in &mut tri.decoder.w1[..lp3d_renderer::triplane::HIDDEN] {
        *w *= 6.0;
    }
    tri.occupancy = Some(Occupancy::bake(&tri, 8).unwrap());
    let settings =
        RenderSettings { depth_resolution: 12, depth_resolution_importance: 12, ..Default::default() };
    let spec = BakeSpec {
        subdivisions: 2,
        fine_subdivisions: 6,
        epsilon: 1e-4,
        max_delta: settings.max_interval(tri.bounds.ray_start, tri.bounds.ray_end),
    };
    let mut fields = Vec::new();
    for choice in [KernelChoice::Fast, KernelChoice::Quick] {
        let renderer = Renderer::with_kernel(&ctx, choice).unwrap();
        let baked = renderer.bake(&renderer.upload(&tri).unwrap(), spec).unwrap();
        let coarse = renderer.read_baked_values(&baked, false).unwrap();
        let fine = renderer.read_baked_values(&baked, true).unwrap();
        fields.push((baked.n_bricks, baked.n_coarse(), coarse, fine));
    }
    let (bricks, n_coarse, coarse, fine) = &fields[0];
    // Not vacuous: both levels hold points, and not all of them zero.
    assert!(*n_coarse > 0 && n_coarse < bricks, "{n_coarse} coarse bricks of {bricks}");
    assert!(coarse.iter().any(|&v| v != 0) && fine.iter().any(|&v| v != 0));
    assert!(fields[0] == fields[1], "the fast and quick kernels baked different fields");
}

/// Exact early termination (`walk_ends` in `shaders/render.wgsl`) ends a walk once its
/// transmittance is too small for any later sample to change an output's float32 sums, or the
/// importance draw: a renderer that walks every sample gives the same bits (exact mode with and
/// without jitter and the importance pass, every output and RGB alone).
#[test]
fn exact_early_termination_changes_no_bit() {
    let ctx = GpuContext::headless().expect("a GPU adapter (lavapipe in CI)");
    let renderer = Renderer::with_kernel(&ctx, KernelChoice::Quick).unwrap();
    // The density row scaled up so that the raw density swings from empty to opaque across the
    // box: rays pass empty stretches, then turn opaque (checked below).
    let mut tri = test_triplane(PlaneDtype::F32);
    tri.decoder.b1[0] = 8.0;
    for w in &mut tri.decoder.w1[..lp3d_renderer::triplane::HIDDEN] {
        *w *= 40.0;
    }
    let gpu = renderer.upload(&tri).unwrap();
    let ended = render_bits(&renderer, &gpu);
    renderer.set_full_walk(true);
    let full = render_bits(&renderer, &gpu);
    // Not vacuous: most rays turn opaque (their weights sum to 1 in float32), so walks do end.
    let wsum = &full[3];
    let opaque = wsum.iter().filter(|&&w| f32::from_bits(w) == 1.0).count();
    assert!(opaque * 2 > wsum.len(), "{opaque} of {} rays opaque", wsum.len());
    assert_same(&ended, &full, "exact early termination vs every sample walked");
}
