//! End-to-end on the real device (lavapipe in CI): a render produces finite outputs with the
//! documented shapes, and the file format round-trips. Numerical parity with the float64
//! reference lives in the Python suite (tests/render/test_render_parity.py).

mod common;

use lp3d_renderer::camera::{FFHQ_FOCAL, FFHQ_RADIUS};
use lp3d_renderer::{Camera, GpuContext, Outputs, PlaneDtype, RenderSettings, Renderer, Triplane};

fn test_triplane(h: usize, w: usize) -> Triplane {
    common::random_triplane(12345, h, w, 1.0, "gpu_smoke")
}

#[test]
fn renders_finite_outputs_and_restricts_outputs() {
    let ctx = GpuContext::headless().expect("a GPU adapter (lavapipe in CI)");
    eprintln!("adapter: {:?}", ctx.adapter_info);
    let renderer = Renderer::new(&ctx).unwrap();
    let tri = test_triplane(16, 16);
    let gpu = renderer.upload(&tri).unwrap();
    let half_pi = std::f64::consts::FRAC_PI_2;
    let cams = vec![
        Camera::lookat_pose(half_pi, half_pi, FFHQ_RADIUS, [0.0, 0.0, 0.0], FFHQ_FOCAL),
        Camera::lookat_pose(half_pi + 0.5, half_pi - 0.2, FFHQ_RADIUS, [0.0, 0.0, 0.2], FFHQ_FOCAL),
    ];
    let settings = RenderSettings {
        resolution: 8,
        depth_resolution: 12,
        depth_resolution_importance: 12,
        ..Default::default()
    };
    let out = renderer.render(&gpu, &cams, &settings, Outputs::ALL).unwrap();
    let features = out.features.unwrap();
    assert_eq!(features.len(), 2 * 32 * 64);
    assert!(features.iter().all(|v| v.is_finite() && (-1.01..=1.01).contains(v)));
    let depth = out.depth.unwrap();
    assert!(depth.iter().all(|d| (2.25..=3.3).contains(d)), "{depth:?}");
    let wsum = out.weights_sum.unwrap();
    assert!(wsum.iter().all(|w| (0.0..=1.0).contains(w)));
    assert!(wsum.iter().any(|w| *w > 0.01));
    // rgb equals the first 3 feature channels, whether or not features are computed.
    let rgb_only = renderer.render(&gpu, &cams, &settings, Outputs::from_names(&["rgb"]).unwrap()).unwrap();
    assert!(rgb_only.features.is_none() && rgb_only.depth.is_none());
    let rgb = rgb_only.rgb.unwrap();
    for b in 0..2 {
        for i in 0..3 * 64 {
            let a = rgb[b * 3 * 64 + i];
            let f = features[b * 32 * 64 + i];
            assert!((a - f).abs() <= 1e-6, "camera {b} index {i}: {a} vs {f}");
        }
    }
}

#[test]
fn triplane_file_round_trips() {
    let dir = std::env::temp_dir().join(format!("lp3d-rt-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for dtype in [PlaneDtype::F32, PlaneDtype::F16] {
        let mut tri = test_triplane(4, 6);
        tri.plane_dtype = dtype;
        if dtype == PlaneDtype::F16 {
            tri.planes = tri.planes.iter().map(|&v| half::f16::from_f32(v).to_f32()).collect();
        }
        tri.camera = Some(Camera::lookat_pose(1.0, 1.5, 2.7, [0.0; 3], 4.2647));
        let path = dir.join("t.npz");
        tri.save(&path).unwrap();
        assert_eq!(Triplane::load(&path).unwrap(), tri);
    }
    let e = Triplane::load(dir.join("missing.npz")).unwrap_err().to_string();
    assert!(e.contains("missing.npz"), "{e}");
    std::fs::write(dir.join("junk.npz"), b"not a zip").unwrap();
    let e = Triplane::load(dir.join("junk.npz")).unwrap_err().to_string();
    assert!(e.contains("zip"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}
