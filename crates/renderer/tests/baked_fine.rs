//! A two-level baked field whose fine bricks outgrow a storage binding (`baked::atlas`): baked in
//! passes, they must come out as one bake would make them. The device's limit is lowered to 1 MiB
//! for one of two renderers on the same device, so that a small scene needs several passes.

mod common;

use lp3d_renderer::camera::{FFHQ_FOCAL, FFHQ_RADIUS};
use lp3d_renderer::{
    BakeSpec, Camera, GpuContext, Occupancy, Outputs, RenderSettings, Renderer, Skips, Triplane,
};

/// A pseudo-random triplane whose raw density sits near 20, so that a surface "crosses" every brick
/// (`baked::needs_fine`) and every brick is fine.
fn dense_triplane() -> Triplane {
    let mut tri = common::random_triplane(777, 8, 8, 1.0, "baked_fine");
    tri.decoder.b1[0] = 20.0;
    tri.occupancy = Some(Occupancy::bake(&tri, 8).unwrap());
    tri
}

#[test]
fn fine_bricks_beyond_a_storage_binding_bake_in_passes_as_in_one() {
    let mut ctx = GpuContext::headless().expect("a GPU adapter (lavapipe in CI)");
    let one_pass = Renderer::new(&ctx).unwrap();
    ctx.limits.max_storage_buffer_binding_size = 1 << 20;
    let passes = Renderer::new(&ctx).unwrap();

    let tri = dense_triplane();
    let settings = RenderSettings {
        resolution: 16,
        depth_resolution: 12,
        depth_resolution_importance: 12,
        skips: Skips {
            occupancy_epsilon: 1e-4,
            baked_subdivisions: 2,
            baked_fine_subdivisions: 8,
            ..Skips::EXACT
        },
        ..Default::default()
    };
    let spec = BakeSpec {
        subdivisions: 2,
        fine_subdivisions: 8,
        epsilon: 1e-4,
        max_delta: settings.max_interval(tri.bounds.ray_start, tri.bounds.ray_end),
    };
    let cams = [Camera::lookat_pose(1.2, 1.4, FFHQ_RADIUS, [0.0, 0.0, 0.0], FFHQ_FOCAL)];
    let mut fine = Vec::new();
    let mut rgb = Vec::new();
    for renderer in [&one_pass, &passes] {
        let gpu = renderer.upload(&tri).unwrap();
        let baked = renderer.bake(&gpu, spec).unwrap();
        assert_eq!(baked.n_coarse(), 0, "every brick is crossed");
        let points = renderer.read_baked_values(&baked, true).unwrap();
        assert_eq!(points.len(), baked.n_bricks * 9usize.pow(3) * 4);
        fine.push(points);
        rgb.push(
            renderer.render(&gpu, &cams, &settings, Outputs::from_names(&["rgb"]).unwrap()).unwrap().rgb,
        );
    }
    // More than one pass: the fine points are larger than the lowered binding.
    assert!(fine[0].len() * 2 > 2 << 20, "{} halves", fine[0].len());
    assert!(fine[0] == fine[1], "the fine points differ between one pass and several");
    assert_eq!(rgb[0], rgb[1]);
    assert!(rgb[0].as_ref().unwrap().iter().all(|v| v.is_finite()));
}
