// Stage: superres (lp3d.nets.superres.FoldedSuperResolution). EG3D's super-resolution network with
// its constant w folded in, so every layer is a plain convolution. Per ×2 block: a stride-2
// transposed 3x3 convolution (sr_conv_up), the [1,3,3,1] FIR filter with bias and lrelu·√2
// (sr_fir_act), a 3x3 convolution with bias and lrelu·√2 (sr_conv), then the image: the previous
// image FIR-upsampled plus a 1x1 ToRGB of the features (sr_rgb). Activations are float32 NCHW, one
// image after another; one dispatch per layer with its sizes in `sr`, images along z. The Rust side
// is `crates/renderer/src/superres.rs` (weights layout, dispatch order).
// needs: nothing
// provides: SR_GROUP, SR_LRELU_SLOPE, SR_LRELU_GAIN, SrLayer, sr, sr_weights, sr_src, sr_dst, sr_skip,
// provides: sr_fir_tap, sr_lrelu, sr_store_group, sr_conv_up, sr_fir_act, sr_conv, sr_rgb

// Output channels one invocation of a convolution computes (two vec4 accumulators); weights are
// stored padded to a multiple of it.
const SR_GROUP: u32 = 8u;
// StyleGAN2's leaky ReLU and its variance-preserving gain (lp3d.nets.stylegan_ops).
const SR_LRELU_SLOPE: f32 = 0.2;
const SR_LRELU_GAIN: f32 = 1.4142135623730951;

struct SrLayer {
    in_channels: u32,
    out_channels: u32,
    // Side of the layer's input (sr_rgb: of the skip image) and of its output.
    in_res: u32,
    out_res: u32,
    // Offsets in vec4s into sr_weights: the layer's weights and its biases.
    weights: u32,
    bias: u32,
    // Channels per image of sr_skip (the feature image's for the first block, 3 after).
    skip_channels: u32,
    // sr_fir_act: the output channel its input's channel 0 is (the transposed convolution runs in
    // chunks of channels when its whole output would not fit one binding).
    first_channel: u32,
}

// Group 2, so that the file joins the render module's files (a web page compiles them all as one
// module) without sharing a binding with groups 0 and 1.
@group(2) @binding(0) var<uniform> sr: SrLayer;
@group(2) @binding(1) var<storage, read> sr_weights: array<vec4<f32>>;
@group(2) @binding(2) var<storage, read> sr_src: array<f32>;
@group(2) @binding(3) var<storage, read_write> sr_dst: array<f32>;
@group(2) @binding(4) var<storage, read> sr_skip: array<f32>;

// One tap of the 1D filter [1,3,3,1]/8 with the ×2 upsampling gain 2 per axis; a 2D tap is the
// product of two (exact in float32, as torch's 2D kernel values are).
fn sr_fir_tap(a: u32) -> f32 {
    return select(0.25, 0.75, a == 1u || a == 2u);
}

fn sr_lrelu(v: f32) -> f32 {
    return select(v * SR_LRELU_SLOPE, v, v >= 0.0) * SR_LRELU_GAIN;
}

// Writes output channels first..first+8 (those below sr.out_channels) of one pixel, `at` the
// pixel's index in a channel's plane of `plane` values.
fn sr_store_group(image: u32, first: u32, at: u32, plane: u32, lo: vec4<f32>, hi: vec4<f32>) {
    for (var k = 0u; k < SR_GROUP; k++) {
        let co = first + k;
        if (co < sr.out_channels) {
            sr_dst[(image * sr.out_channels + co) * plane + at] = select(hi[k & 3u], lo[k & 3u], k < 4u);
        }
    }
}

// torch's conv_transpose2d(x, W, stride=2) with W (out, in, 3, 3) = FoldedSuperResolution.convs_up:
// in_res r -> out_res 2r + 1. One invocation per input position (iy, ix) in 0..=r writes the 2x2
// outputs (2iy + {0,1}, 2ix + {0,1}) that read x[iy|iy-1, ix|ix-1], for SR_GROUP output channels.
// Weights: [group][in channel][tap ky*3+kx][SR_GROUP floats].
@compute @workgroup_size(64)
fn sr_conv_up(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    let r = sr.in_res;
    let side = r + 1u;
    if (gid.x >= side * side) {
        return;
    }
    let iy = gid.x / side;
    let ix = gid.x % side;
    let image = wid.z;
    let cin = sr.in_channels;
    let plane = r * r;
    // x[iy, ix], x[iy, ix-1], x[iy-1, ix], x[iy-1, ix-1], zero outside the input.
    let m00 = f32(iy < r && ix < r);
    let m01 = f32(iy < r && ix > 0u);
    let m10 = f32(iy > 0u && ix < r);
    let m11 = f32(iy > 0u && ix > 0u);
    let y0 = min(iy, r - 1u) * r;
    let y1 = (max(iy, 1u) - 1u) * r;
    let x0 = min(ix, r - 1u);
    let x1 = max(ix, 1u) - 1u;
    var ee0 = vec4<f32>(0.0);
    var ee1 = vec4<f32>(0.0);
    var eo0 = vec4<f32>(0.0);
    var eo1 = vec4<f32>(0.0);
    var oe0 = vec4<f32>(0.0);
    var oe1 = vec4<f32>(0.0);
    var oo0 = vec4<f32>(0.0);
    var oo1 = vec4<f32>(0.0);
    var w = sr.weights + wid.y * cin * 18u;
    var base = image * cin * plane;
    for (var ci = 0u; ci < cin; ci++) {
        let v00 = sr_src[base + y0 + x0] * m00;
        let v01 = sr_src[base + y0 + x1] * m01;
        let v10 = sr_src[base + y1 + x0] * m10;
        let v11 = sr_src[base + y1 + x1] * m11;
        // Taps (ky, kx) at w + 2 (3 ky + kx).
        ee0 += v00 * sr_weights[w] + v01 * sr_weights[w + 4u] + v10 * sr_weights[w + 12u]
            + v11 * sr_weights[w + 16u];
        ee1 += v00 * sr_weights[w + 1u] + v01 * sr_weights[w + 5u] + v10 * sr_weights[w + 13u]
            + v11 * sr_weights[w + 17u];
        eo0 += v00 * sr_weights[w + 2u] + v10 * sr_weights[w + 14u];
        eo1 += v00 * sr_weights[w + 3u] + v10 * sr_weights[w + 15u];
        oe0 += v00 * sr_weights[w + 6u] + v01 * sr_weights[w + 10u];
        oe1 += v00 * sr_weights[w + 7u] + v01 * sr_weights[w + 11u];
        oo0 += v00 * sr_weights[w + 8u];
        oo1 += v00 * sr_weights[w + 9u];
        w += 18u;
        base += plane;
    }
    let m = sr.out_res;
    let first = wid.y * SR_GROUP;
    let at = 2u * iy * m + 2u * ix;
    sr_store_group(image, first, at, m * m, ee0, ee1);
    if (ix < r) {
        sr_store_group(image, first, at + 1u, m * m, eo0, eo1);
    }
    if (iy < r) {
        sr_store_group(image, first, at + m, m * m, oe0, oe1);
        if (ix < r) {
            sr_store_group(image, first, at + m + 1u, m * m, oo0, oo1);
        }
    }
}

// The FIR filter after the transposed convolution (padding 1 on each side: in_res 2r + 1 -> out_res
// 2r), then bias and lrelu·√2. One invocation per output value; channel along y. The input holds
// in_channels channels (a chunk), written to output channels first_channel.. of out_channels.
@compute @workgroup_size(64)
fn sr_fir_act(@builtin(global_invocation_id) gid: vec3<u32>) {
    let n = sr.out_res;
    if (gid.x >= n * n) {
        return;
    }
    let py = i32(gid.x / n);
    let px = i32(gid.x % n);
    let m = i32(sr.in_res);
    let co = sr.first_channel + gid.y;
    let base = (gid.z * sr.in_channels + gid.y) * sr.in_res * sr.in_res;
    var acc = 0.0;
    for (var a = 0u; a < 4u; a++) {
        let yy = py + i32(a) - 1;
        let my = f32(yy >= 0 && yy < m);
        let row = base + u32(clamp(yy, 0, m - 1) * m);
        var along = 0.0;
        for (var b = 0u; b < 4u; b++) {
            let xx = px + i32(b) - 1;
            let mx = f32(xx >= 0 && xx < m);
            along += sr_fir_tap(b) * mx * sr_src[row + u32(clamp(xx, 0, m - 1))];
        }
        acc += sr_fir_tap(a) * my * along;
    }
    let bias = sr_weights[sr.bias + co / 4u][co & 3u];
    sr_dst[(gid.z * sr.out_channels + co) * n * n + gid.x] = sr_lrelu(acc + bias);
}

// A 3x3 convolution with padding 1 (out_res = in_res, even), bias and lrelu·√2. One invocation
// computes SR_GROUP output channels of two horizontally adjacent pixels, so that each weight read
// serves both; weights laid out as sr_conv_up's. The group and image come from the workgroup's id,
// so that the weight reads are the same for every invocation of a workgroup.
@compute @workgroup_size(64)
fn sr_conv(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    let n = sr.out_res;
    let half = n / 2u;
    if (gid.x >= n * half) {
        return;
    }
    let py = gid.x / half;
    let px = 2u * (gid.x % half);
    let cin = sr.in_channels;
    let plane = n * n;
    // Rows of the 3x3 windows and columns px - 1 .. px + 2, clamped, and whether each is inside.
    let r0 = (max(py, 1u) - 1u) * n;
    let r1 = py * n;
    let r2 = min(py + 1u, n - 1u) * n;
    let c0 = max(px, 1u) - 1u;
    let c3 = min(px + 2u, n - 1u);
    let my0 = f32(py > 0u);
    let my2 = f32(py + 1u < n);
    let mx0 = f32(px > 0u);
    let mx3 = f32(px + 2u < n);
    var lo0 = vec4<f32>(0.0);
    var hi0 = vec4<f32>(0.0);
    var lo1 = vec4<f32>(0.0);
    var hi1 = vec4<f32>(0.0);
    var w = sr.weights + wid.y * cin * 18u;
    var base = wid.z * cin * plane;
    for (var ci = 0u; ci < cin; ci++) {
        for (var ky = 0u; ky < 3u; ky++) {
            let row = base + select(select(r2, r1, ky == 1u), r0, ky == 0u);
            let my = select(select(my2, 1.0, ky == 1u), my0, ky == 0u);
            let a = sr_src[row + c0] * (my * mx0);
            let b = sr_src[row + px] * my;
            let c = sr_src[row + px + 1u] * my;
            let d = sr_src[row + c3] * (my * mx3);
            let wl0 = sr_weights[w];
            let wh0 = sr_weights[w + 1u];
            let wl1 = sr_weights[w + 2u];
            let wh1 = sr_weights[w + 3u];
            let wl2 = sr_weights[w + 4u];
            let wh2 = sr_weights[w + 5u];
            lo0 += a * wl0 + b * wl1 + c * wl2;
            hi0 += a * wh0 + b * wh1 + c * wh2;
            lo1 += b * wl0 + c * wl1 + d * wl2;
            hi1 += b * wh0 + c * wh1 + d * wh2;
            w += 6u;
        }
        base += plane;
    }
    let bias = sr.bias + wid.y * 2u;
    let bl = sr_weights[bias];
    let bh = sr_weights[bias + 1u];
    for (var k = 0u; k < 4u; k++) {
        lo0[k] = sr_lrelu(lo0[k] + bl[k]);
        hi0[k] = sr_lrelu(hi0[k] + bh[k]);
        lo1[k] = sr_lrelu(lo1[k] + bl[k]);
        hi1[k] = sr_lrelu(hi1[k] + bh[k]);
    }
    let at = py * n + px;
    sr_store_group(wid.z, wid.y * SR_GROUP, at, plane, lo0, hi0);
    sr_store_group(wid.z, wid.y * SR_GROUP, at + 1u, plane, lo1, hi1);
}

// The block's image: the previous image (sr_skip, the first 3 of its skip_channels, side in_res)
// FIR-upsampled ×2 (zeros inserted, padding 2 before and 1 after), plus the 1x1 ToRGB of the block's
// features (sr_src, in_channels at out_res) and its bias. Weights: one vec4 (r, g, b, 0) per input
// channel; the bias one vec4.
@compute @workgroup_size(64)
fn sr_rgb(@builtin(global_invocation_id) gid: vec3<u32>) {
    let n = sr.out_res;
    if (gid.x >= n * n) {
        return;
    }
    let py = i32(gid.x / n);
    let px = i32(gid.x % n);
    let r = i32(sr.in_res);
    let skip_plane = sr.in_res * sr.in_res;
    let skip_base = gid.z * sr.skip_channels * skip_plane;
    var up = vec3<f32>(0.0);
    for (var a = 0u; a < 4u; a++) {
        // Row py + a - 2 of the zero-inserted image holds a value when it is even.
        let yy = py + i32(a) - 2;
        let my = f32(yy >= 0 && (yy & 1) == 0 && yy / 2 < r);
        let row = u32(clamp(yy / 2, 0, r - 1)) * sr.in_res;
        for (var b = 0u; b < 4u; b++) {
            let xx = px + i32(b) - 2;
            let mx = f32(xx >= 0 && (xx & 1) == 0 && xx / 2 < r);
            let at = skip_base + row + u32(clamp(xx / 2, 0, r - 1));
            let v = vec3<f32>(sr_skip[at], sr_skip[at + skip_plane], sr_skip[at + 2u * skip_plane]);
            up += (sr_fir_tap(a) * sr_fir_tap(b) * my * mx) * v;
        }
    }
    let c = sr.in_channels;
    let plane = n * n;
    var base = gid.z * c * plane + gid.x;
    var acc = vec4<f32>(0.0);
    for (var ci = 0u; ci < c; ci++) {
        acc += sr_src[base] * sr_weights[sr.weights + ci];
        base += plane;
    }
    let rgb = up + (acc.xyz + sr_weights[sr.bias].xyz);
    let out = gid.z * 3u * plane + gid.x;
    sr_dst[out] = rgb.x;
    sr_dst[out + plane] = rgb.y;
    sr_dst[out + 2u * plane] = rgb.z;
}
