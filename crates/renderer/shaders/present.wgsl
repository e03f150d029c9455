// Stage: present (lp3d.images for the same mappings on the CPU). Maps one render output of
// camera 0 to an RGBA8 storage texture (the viewer shows it directly, no readback). Group 1
// holds the target and what to show.
// needs: params, out_features, out_depth, out_weights_sum
// provides: DISPLAY_RGB, DISPLAY_DEPTH, DISPLAY_WEIGHTS, DISPLAY_CHANNEL, Display, display_target,
// provides: display, to_unit, present

const DISPLAY_RGB: u32 = 0u;
const DISPLAY_DEPTH: u32 = 1u;
const DISPLAY_WEIGHTS: u32 = 2u;
const DISPLAY_CHANNEL: u32 = 3u;

struct Display {
    mode: u32,
    // Feature channel shown in DISPLAY_CHANNEL mode (0..32), index into out_features.
    channel: u32,
    // Depth mapped to [bright, dark] over [depth_near, depth_far].
    depth_near: f32,
    depth_far: f32,
}

@group(1) @binding(0) var display_target: texture_storage_2d<rgba8unorm, write>;
@group(1) @binding(1) var<uniform> display: Display;

fn to_unit(v: f32) -> f32 {
    return clamp((v + 1.0) * 0.5, 0.0, 1.0);
}

@compute @workgroup_size(8, 8)
fn present(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = params.resolution;
    if (gid.x >= r || gid.y >= r) {
        return;
    }
    let n_pix = r * r;
    let pixel = gid.y * r + gid.x;
    var color = vec3<f32>(0.0);
    switch display.mode {
        case DISPLAY_RGB: {
            color = vec3<f32>(
                to_unit(out_features[pixel]),
                to_unit(out_features[n_pix + pixel]),
                to_unit(out_features[2u * n_pix + pixel]),
            );
        }
        case DISPLAY_DEPTH: {
            // Same ramp as lp3d.images.depth_to_uint8: near bright, empty rays black.
            let t = clamp((display.depth_far - out_depth[pixel]) / max(display.depth_far - display.depth_near, 1e-6), 0.0, 1.0);
            color = clamp(vec3<f32>(3.0 * t, 3.0 * t - 1.0, 3.0 * t - 2.0), vec3<f32>(0.0), vec3<f32>(1.0));
            if (out_weights_sum[pixel] < 0.5) {
                color = vec3<f32>(0.0);
            }
        }
        case DISPLAY_WEIGHTS: {
            color = vec3<f32>(clamp(out_weights_sum[pixel], 0.0, 1.0));
        }
        default: {
            color = vec3<f32>(to_unit(out_features[display.channel * n_pix + pixel]));
        }
    }
    textureStore(display_target, vec2<i32>(i32(gid.x), i32(gid.y)), vec4<f32>(color, 1.0));
}
