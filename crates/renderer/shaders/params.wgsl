// Stage: bindings and uniforms shared by every kernel of the renderer. First in every module.
// The Rust mirror is `crates/renderer/src/gpu_types.rs`; a test checks the sizes match.
// needs: nothing
// provides: MAX_SAMPLES, N_CHANNELS, HIDDEN, FLAG_JITTER, FLAG_WHITE_BACK, FLAG_HALF_PLANES,
// provides: FLAG_OCCUPANCY_COARSE, FLAG_FULL_WALK, Params, Decoder, params, cameras, planes, decoder,
// provides: out_features, out_depth, out_weights_sum, depth_bounds, occupancy_bits, baked,
// provides: baked_fine, bake_cells, bake_out

// Largest coarse or fine sample count per ray (per-invocation scratch arrays).
const MAX_SAMPLES: u32 = 256u;
// Channels per plane / decoder input, decoder hidden width.
const N_CHANNELS: u32 = 32u;
const HIDDEN: u32 = 64u;

const FLAG_JITTER: u32 = 1u;
const FLAG_WHITE_BACK: u32 = 2u;
// Planes are packed float16 pairs (the triplane's planes were float16).
const FLAG_HALF_PLANES: u32 = 4u;
// The occupancy skip applies to the coarse pass too (not only the final composite).
const FLAG_OCCUPANCY_COARSE: u32 = 8u;
// Walk every sample: no exact early termination (render.wgsl's walk_ends; the outputs are the
// same bits either way, which tests check with it).
const FLAG_FULL_WALK: u32 = 16u;

// Per-render settings. Field names follow EG3D's rendering_kwargs.
struct Params {
    resolution: u32,
    depth_resolution: u32,
    depth_resolution_importance: u32,
    // First camera of this dispatch within the batch (large batches are split).
    camera_offset: u32,
    plane_h: u32,
    plane_w: u32,
    // Feature channels decoded and written: 32 (features), 3 (rgb only) or 0.
    feature_channels: u32,
    flags: u32,
    ray_start: f32,
    ray_end: f32,
    box_warp: f32,
    seed: u32,
    // torch.linspace's float32 step, (f32(end) - f32(start)) / (S - 1) in float32.
    lin_step: f32,
    // EG3D's jitter step, (ray_end - ray_start) / (S - 1) in float64, rounded.
    jitter_step: f32,
    // torch.linspace(0, 1, N)'s float32 step, for the det=True importance draw.
    u_step: f32,
    // Cameras in the whole batch (the depth clamp is batch-global, as in EG3D).
    n_cameras: u32,
    // Skips (0 = exact EG3D semantics). Early ray termination below this transmittance:
    transmittance_threshold: f32,
    // No importance pass for rays whose coarse opacity is below this:
    empty_threshold: f32,
    // Occupancy grid cells per axis (docs/occupancy.md); 0 = no occupancy skip.
    occupancy_resolution: u32,
    // Baked-field points per cell edge, k (docs/baked.md); 0 = decode every sample.
    baked_subdivisions: u32,
    // The baked field's cells per axis (the occupancy grid's, or a coarser one they tile).
    baked_cells: u32,
    // Where the points start in `baked` (u32 words: after the G^3 index).
    baked_values_offset: u32,
    // Two-level fields (docs/baked.md, "Two levels"): the fine bricks' points per cell edge (their
    // cells are flagged in `baked`, their points are in `baked_fine`).
    baked_fine_subdivisions: u32,
    // A uniform's size is a multiple of 16 bytes.
    pad: u32,
}

// EG3D OSGDecoder with effective weights, packed as vec4 rows for uniform layout.
struct Decoder {
    w0: array<vec4<f32>, 512>, // hidden unit j: w0[8j .. 8j+8] (64 x 32)
    b0: array<vec4<f32>, 16>,  // 64
    w1: array<vec4<f32>, 528>, // output r: w1[16r .. 16r+16] (33 x 64)
    b1: array<vec4<f32>, 9>,   // 33, padded to 36
}

@group(0) @binding(0) var<uniform> params: Params;
// 25 floats per camera: cam2world 4x4 row-major, then 3x3 normalised intrinsics.
@group(0) @binding(1) var<storage, read> cameras: array<f32>;
// Planes channel-last: texel (p, y, x) holds 32 channels, as 8 vec4 of float32 bits, or with
// FLAG_HALF_PLANES as 4 vec4 of packed float16 pairs (channel 2i low, 2i + 1 high).
@group(0) @binding(2) var<storage, read> planes: array<vec4<u32>>;
@group(0) @binding(3) var<uniform> decoder: Decoder;
// Outputs of this dispatch: features (cameras, feature_channels, R, R), depth and weights sum (cameras, R, R).
@group(0) @binding(4) var<storage, read_write> out_features: array<f32>;
@group(0) @binding(5) var<storage, read_write> out_depth: array<f32>;
@group(0) @binding(6) var<storage, read_write> out_weights_sum: array<f32>;
// Batch-global [min, max] of all sample depths, as float bits (depths are >= 0, so bit order = value order).
@group(0) @binding(7) var<storage, read_write> depth_bounds: array<atomic<u32>, 2>;
// Occupancy bits, one per grid cell (ix * G + iy) * G + iz: set = the cell may hold density.
@group(0) @binding(8) var<storage, read> occupancy_bits: array<u32>;
// The baked field (docs/baked.md), one buffer so that render_rays keeps to WebGPU's default of 8
// storage buffers per stage: per baked cell the number of its brick or BAKED_EMPTY (G^3 words),
// then from baked_values_offset per (coarse) brick (k + 1)^3 points of two words, (sigma_raw, r)
// and (g, b) as packed float16 pairs.
@group(0) @binding(9) var<storage, read> baked: array<u32>;
// A two-level field's fine bricks, (k_f + 1)^3 texels each, side by side in a 3D texture (no
// storage binding is large enough for them; crates/renderer/src/baked/atlas.rs): a texel is a
// point, (sigma_raw, r, g, b) as in `baked`.
@group(0) @binding(10) var baked_fine: texture_3d<f32>;
// The bake's own bindings: the cell of each brick, and the field it writes the points into.
@group(0) @binding(11) var<storage, read> bake_cells: array<u32>;
@group(0) @binding(12) var<storage, read_write> bake_out: array<u32>;
