//! The folded network laid out for the kernels: its weights packed into one buffer of vec4s and
//! each layer's uniform, made once per network.

use bytemuck::Zeroable;
use wgpu::util::DeviceExt;

use super::{SrLayer, SuperresBlock, SuperresWeights, GROUP};

/// One block's layers: their uniforms (made once) and sizes.
pub(super) struct BlockPlan {
    pub(super) channels: usize,
    /// Input side r (output 2r).
    pub(super) res: usize,
    /// The transposed convolution and its FIR filter by chunks of output channels: the chunk's
    /// channel count and the uniforms of its sr_conv_up and sr_fir_act.
    pub(super) chunks: Vec<(usize, wgpu::Buffer, wgpu::Buffer)>,
    /// Uniforms of sr_conv and sr_rgb.
    pub(super) conv: wgpu::Buffer,
    pub(super) rgb: wgpu::Buffer,
}

/// Floats per image of the scratch activations: the largest block input or output, or the
/// transposed convolution's output ((2r + 1)² per channel) of one group of channels when that is
/// larger. That output is made in chunks of channels that fit in as much (`chunk_channels`).
pub(super) fn scratch_floats(weights: &SuperresWeights) -> usize {
    let (mut cin, mut r, mut most) = (weights.in_channels, weights.input_resolution, 0);
    for b in &weights.blocks {
        let c = b.channels;
        most = most.max(cin * r * r).max(c * 4 * r * r).max(c.min(GROUP) * (2 * r + 1) * (2 * r + 1));
        cin = c;
        r *= 2;
    }
    most
}

/// Output channels per chunk of a transposed convolution of width `c` from side `r`: all of them
/// when they fit in `floats` per image, else the most whole groups of `GROUP` that do.
fn chunk_channels(c: usize, r: usize, floats: usize) -> usize {
    let per_channel = (2 * r + 1) * (2 * r + 1);
    if c * per_channel <= floats {
        c
    } else {
        // `scratch_floats` makes room for at least one group.
        (floats / per_channel / GROUP * GROUP).max(GROUP)
    }
}

/// The packed weights, each block's plan and the floats per image of a scratch activation.
pub(super) fn plan(
    device: &wgpu::Device,
    weights: &SuperresWeights,
) -> (Vec<[f32; 4]>, Vec<BlockPlan>, usize) {
    let mut packed: Vec<[f32; 4]> = Vec::new();
    let floats = scratch_floats(weights);
    let (mut cin, mut res) = (weights.in_channels, weights.input_resolution);
    let mut plans = Vec::new();
    for (i, b) in weights.blocks.iter().enumerate() {
        let skip_channels = if i == 0 { weights.in_channels } else { 3 };
        plans.push(plan_block(device, &mut packed, b, cin, res, skip_channels, floats));
        cin = b.channels;
        res *= 2;
    }
    (packed, plans, floats)
}

/// One block from side `res` and `cin` channels: its weights appended to `packed`, its uniforms.
fn plan_block(
    device: &wgpu::Device,
    packed: &mut Vec<[f32; 4]>,
    b: &SuperresBlock,
    cin: usize,
    res: usize,
    skip_channels: usize,
    floats: usize,
) -> BlockPlan {
    let uniform = |l: SrLayer| {
        device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lp3d superres layer"),
            contents: bytemuck::bytes_of(&l),
            usage: wgpu::BufferUsages::UNIFORM,
        })
    };
    let c = b.channels;
    let conv_up = pack_conv(packed, &b.conv_up, c, cin);
    let bias_up = pack_bias(packed, &b.bias_up);
    let conv = pack_conv(packed, &b.conv, c, c);
    let bias = pack_bias(packed, &b.bias);
    let rgb = packed.len();
    packed.extend((0..c).map(|ci| [b.rgb_weight[ci], b.rgb_weight[c + ci], b.rgb_weight[2 * c + ci], 0.0]));
    let rgb_bias = packed.len();
    packed.push([b.rgb_bias[0], b.rgb_bias[1], b.rgb_bias[2], 0.0]);
    let u = |v: usize| v as u32;
    let r = u(res);
    let step = chunk_channels(c, res, floats);
    let chunks = (0..c)
        .step_by(step)
        .map(|first| {
            let n = step.min(c - first);
            // The chunk's groups start `first / GROUP` groups into the packed weight.
            let at = conv_up + first / GROUP * cin * 18;
            let up = SrLayer {
                in_channels: u(cin),
                out_channels: u(n),
                in_res: r,
                out_res: 2 * r + 1,
                weights: u(at),
                ..SrLayer::zeroed()
            };
            let fir = SrLayer {
                in_channels: u(n),
                out_channels: u(c),
                in_res: 2 * r + 1,
                out_res: 2 * r,
                bias: u(bias_up),
                first_channel: u(first),
                ..SrLayer::zeroed()
            };
            (n, uniform(up), uniform(fir))
        })
        .collect();
    let conv = uniform(SrLayer {
        in_channels: u(c),
        out_channels: u(c),
        in_res: 2 * r,
        out_res: 2 * r,
        weights: u(conv),
        bias: u(bias),
        ..SrLayer::zeroed()
    });
    let rgb = uniform(SrLayer {
        in_channels: u(c),
        out_channels: 3,
        in_res: r,
        out_res: 2 * r,
        weights: u(rgb),
        bias: u(rgb_bias),
        skip_channels: u(skip_channels),
        first_channel: 0,
    });
    BlockPlan { channels: c, res, chunks, conv, rgb }
}

/// Appends a (c, cin, 3, 3) weight in the kernels' layout, [group][cin][tap][GROUP], zero-padded
/// to whole groups; its offset in vec4s.
fn pack_conv(packed: &mut Vec<[f32; 4]>, w: &[f32], c: usize, cin: usize) -> usize {
    let at = packed.len();
    for g in 0..c.div_ceil(GROUP) {
        for ci in 0..cin {
            for t in 0..9 {
                let v = |k: usize| {
                    let co = g * GROUP + k;
                    if co < c {
                        w[(co * cin + ci) * 9 + t]
                    } else {
                        0.0
                    }
                };
                packed.push([v(0), v(1), v(2), v(3)]);
                packed.push([v(4), v(5), v(6), v(7)]);
            }
        }
    }
    at
}

/// Appends biases zero-padded to whole groups; their offset in vec4s.
fn pack_bias(packed: &mut Vec<[f32; 4]>, b: &[f32]) -> usize {
    let at = packed.len();
    let padded = b.len().div_ceil(GROUP) * GROUP;
    let v = |i: usize| b.get(i).copied().unwrap_or(0.0);
    packed.extend((0..padded / 4).map(|q| [v(4 * q), v(4 * q + 1), v(4 * q + 2), v(4 * q + 3)]));
    at
}
