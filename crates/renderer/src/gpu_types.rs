//! Plain-old-data mirrors of the WGSL uniforms in `shaders/params.wgsl`. Field order and
//! sizes must match the WGSL structs; `tests/shaders.rs` (`uniform_layouts_match_wgsl`) checks
//! them with naga.

use bytemuck::{Pod, Zeroable};

use crate::settings::{Display, RenderSettings};
use crate::triplane::{Decoder, SceneInfo, HIDDEN, N_CHANNELS, N_OUT};

pub const FLAG_JITTER: u32 = 1;
pub const FLAG_WHITE_BACK: u32 = 2;
/// Planes are packed float16 pairs (`shaders/triplane.wgsl`).
pub const FLAG_HALF_PLANES: u32 = 4;
/// The occupancy skip applies to the coarse pass too.
pub const FLAG_OCCUPANCY_COARSE: u32 = 8;
/// Walk every sample: no exact early termination (`shaders/render.wgsl`'s `walk_ends`). The
/// outputs are the same bits either way; tests and benchmarks compare the two with it.
pub const FLAG_FULL_WALK: u32 = 16;

/// Mirrors `struct Params` in `shaders/params.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct Params {
    pub resolution: u32,
    pub depth_resolution: u32,
    pub depth_resolution_importance: u32,
    pub camera_offset: u32,
    pub plane_h: u32,
    pub plane_w: u32,
    pub feature_channels: u32,
    pub flags: u32,
    pub ray_start: f32,
    pub ray_end: f32,
    pub box_warp: f32,
    pub seed: u32,
    pub lin_step: f32,
    pub jitter_step: f32,
    pub u_step: f32,
    pub n_cameras: u32,
    pub transmittance_threshold: f32,
    pub empty_threshold: f32,
    /// Occupancy grid cells per axis; 0 = no occupancy skip.
    pub occupancy_resolution: u32,
    pub baked_subdivisions: u32,
    pub baked_cells: u32,
    pub baked_values_offset: u32,
    /// Two-level fields: the fine bricks' points per cell edge.
    pub baked_fine_subdivisions: u32,
    pub pad: u32,
}

impl Params {
    pub fn new(tri: &SceneInfo, settings: &RenderSettings, feature_channels: u32, n_cameras: u32) -> Params {
        let s = settings.depth_resolution;
        let n = settings.depth_resolution_importance;
        let mut flags = 0;
        if !settings.deterministic {
            flags |= FLAG_JITTER;
        }
        if settings.white_back {
            flags |= FLAG_WHITE_BACK;
        }
        if settings.skips.occupancy_coarse {
            flags |= FLAG_OCCUPANCY_COARSE;
        }
        Params {
            resolution: settings.resolution,
            depth_resolution: s,
            depth_resolution_importance: n,
            camera_offset: 0,
            plane_h: tri.height,
            plane_w: tri.width,
            feature_channels,
            flags,
            ray_start: tri.bounds.ray_start,
            ray_end: tri.bounds.ray_end,
            box_warp: tri.bounds.box_warp,
            seed: settings.seed,
            // torch.linspace's float32 step (computed in float32, as torch does on the CPU).
            lin_step: (tri.bounds.ray_end - tri.bounds.ray_start) / (s - 1) as f32,
            // EG3D's jitter scale: a Python float (float64) rounded once.
            jitter_step: ((tri.bounds.ray_end as f64 - tri.bounds.ray_start as f64) / (s - 1) as f64) as f32,
            u_step: if n > 1 { 1.0f32 / (n - 1) as f32 } else { 0.0 },
            n_cameras,
            transmittance_threshold: settings.skips.transmittance_threshold,
            empty_threshold: settings.skips.empty_threshold,
            occupancy_resolution: 0,
            baked_subdivisions: 0,
            baked_cells: 0,
            baked_values_offset: 0,
            baked_fine_subdivisions: 0,
            pad: 0,
        }
    }
}

/// Mirrors `struct Decoder` in `shaders/params.wgsl`: weights as vec4 rows, biases padded.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct DecoderUniform {
    pub w0: [[f32; 4]; HIDDEN * N_CHANNELS / 4],
    pub b0: [[f32; 4]; HIDDEN / 4],
    pub w1: [[f32; 4]; N_OUT * HIDDEN / 4],
    pub b1: [[f32; 4]; N_OUT.div_ceil(4)],
}

impl DecoderUniform {
    pub fn from_decoder(d: &Decoder) -> Self {
        let mut u = DecoderUniform::zeroed();
        bytemuck::cast_slice_mut::<[f32; 4], f32>(&mut u.w0).copy_from_slice(&d.w0);
        bytemuck::cast_slice_mut::<[f32; 4], f32>(&mut u.b0).copy_from_slice(&d.b0);
        bytemuck::cast_slice_mut::<[f32; 4], f32>(&mut u.w1).copy_from_slice(&d.w1);
        bytemuck::cast_slice_mut::<[f32; 4], f32>(&mut u.b1)[..N_OUT].copy_from_slice(&d.b1);
        u
    }
}

/// Mirrors `struct Display` in `shaders/present.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct DisplayUniform {
    pub mode: u32,
    pub channel: u32,
    pub depth_near: f32,
    pub depth_far: f32,
}

impl DisplayUniform {
    pub fn new(display: Display) -> Self {
        let (mode, channel, depth_near, depth_far) = match display {
            Display::Rgb => (0, 0, 0.0, 1.0),
            Display::Depth { near, far } => (1, 0, near, far),
            Display::Weights => (2, 0, 0.0, 1.0),
            Display::Channel(c) => (3, c, 0.0, 1.0),
        };
        DisplayUniform { mode, channel, depth_near, depth_far }
    }
}
