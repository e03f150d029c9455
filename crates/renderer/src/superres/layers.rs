//! The folded network laid out for the kernels ([`NetworkPlan`]): its weights packed into one
//! buffer of vec4s and its dispatches with their uniforms, made once per network, as plain data
//! that the native renderer records and the web page runs.

use bytemuck::Zeroable;

use super::{SrLayer, SuperresBlock, SuperresWeights, GROUP, WORKGROUP};
use crate::shaders;

/// Which buffer of a frame a step binds (`SuperresFrame`; the page's twin in `share/gpu.js`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Slot {
    /// The feature images the network reads (a render's, or `apply`'s upload).
    Features,
    /// A block's features (the conv's output, the next block's input).
    X,
    /// The transposed convolution's output.
    Up,
    /// Its filtered, activated form.
    Act,
    /// The two images, ping-ponged from block to block.
    ImageA,
    ImageB,
    /// Nothing (a kernel that reads no skip image).
    Empty,
}

impl Slot {
    pub fn name(self) -> &'static str {
        match self {
            Slot::Features => "features",
            Slot::X => "x",
            Slot::Up => "up",
            Slot::Act => "act",
            Slot::ImageA => "image_a",
            Slot::ImageB => "image_b",
            Slot::Empty => "empty",
        }
    }
}

/// The four kernels of `shaders/superres.wgsl`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SrKernel {
    ConvUp,
    FirAct,
    Conv,
    Rgb,
}

impl SrKernel {
    /// Its entry point.
    pub fn name(self) -> &'static str {
        match self {
            SrKernel::ConvUp => shaders::SR_CONV_UP.name,
            SrKernel::FirAct => shaders::SR_FIR_ACT.name,
            SrKernel::Conv => shaders::SR_CONV.name,
            SrKernel::Rgb => shaders::SR_RGB.name,
        }
    }
}

/// One dispatch: a kernel with its layer uniform, the buffers it binds (source, destination,
/// skip image) and its workgroups in x and y (z is the batch's images).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Step {
    pub kernel: SrKernel,
    pub layer: SrLayer,
    pub src: Slot,
    pub dst: Slot,
    pub skip: Slot,
    pub workgroups: [u32; 2],
}

/// A folded network laid out for the kernels, once per network: its weights packed into vec4s
/// and its dispatches in order. The native renderer records it (`SuperRes::record`); the web page
/// runs the same plan (`SuperRes::plan`, handed over by `lp3d share`).
#[derive(Debug, Clone, PartialEq)]
pub struct NetworkPlan {
    pub packed: Vec<[f32; 4]>,
    pub steps: Vec<Step>,
    /// Floats per image of each scratch activation (`Slot::X`, `Up`, `Act`).
    pub scratch_floats: usize,
    /// Floats per image of each image (`Slot::ImageA`, `ImageB`).
    pub image_floats: usize,
    /// Where the last block's image lands.
    pub output: Slot,
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

/// The network's plan: its weights packed, its dispatches in order.
pub fn plan(weights: &SuperresWeights) -> NetworkPlan {
    let mut packed: Vec<[f32; 4]> = Vec::new();
    let floats = scratch_floats(weights);
    let (mut cin, mut res) = (weights.in_channels, weights.input_resolution);
    let mut steps = Vec::new();
    let image = |i: usize| if i % 2 == 0 { Slot::ImageA } else { Slot::ImageB };
    for (i, b) in weights.blocks.iter().enumerate() {
        // x_in -> (conv_up) -> up -> (fir) -> act, by chunks of channels; act -> (conv) -> x,
        // which the next block reads (x_in is dead once every chunk has read it).
        let (x_in, skip, skip_channels) = if i == 0 {
            (Slot::Features, Slot::Features, weights.in_channels)
        } else {
            (Slot::X, image(i + 1), 3)
        };
        let slots = BlockSlots { x_in, skip, skip_channels, image: image(i) };
        plan_block(&mut steps, &mut packed, b, cin, res, floats, slots);
        cin = b.channels;
        res *= 2;
    }
    let output = image(weights.blocks.len() - 1);
    NetworkPlan { packed, steps, scratch_floats: floats, image_floats: 3 * res * res, output }
}

/// Where a block reads and writes, by its place in the network.
struct BlockSlots {
    /// Its input features: the network's for the first block, the previous block's after.
    x_in: Slot,
    /// The image it upsamples and adds to: the feature image's rgb for the first block.
    skip: Slot,
    skip_channels: usize,
    /// Where its image lands.
    image: Slot,
}

/// One block from side `res` and `cin` channels: its weights appended to `packed`, its steps to
/// `steps`.
// Long because: the block's four layers are laid out in dispatch order, each uniform beside the
// offsets into `packed` it reads; split, the offsets would travel between functions.
fn plan_block(
    steps: &mut Vec<Step>,
    packed: &mut Vec<[f32; 4]>,
    b: &SuperresBlock,
    cin: usize,
    res: usize,
    floats: usize,
    slots: BlockSlots,
) {
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
    let groups = |n: usize| u(n.div_ceil(GROUP));
    let pixels = |side: u32| (side * side).div_ceil(WORKGROUP);
    let step = chunk_channels(c, res, floats);
    for first in (0..c).step_by(step) {
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
        steps.push(Step {
            kernel: SrKernel::ConvUp,
            layer: up,
            src: slots.x_in,
            dst: Slot::Up,
            skip: Slot::Empty,
            workgroups: [pixels(r + 1), groups(n)],
        });
        let fir = SrLayer {
            in_channels: u(n),
            out_channels: u(c),
            in_res: 2 * r + 1,
            out_res: 2 * r,
            bias: u(bias_up),
            first_channel: u(first),
            ..SrLayer::zeroed()
        };
        steps.push(Step {
            kernel: SrKernel::FirAct,
            layer: fir,
            src: Slot::Up,
            dst: Slot::Act,
            skip: Slot::Empty,
            workgroups: [pixels(2 * r), u(n)],
        });
    }
    let conv = SrLayer {
        in_channels: u(c),
        out_channels: u(c),
        in_res: 2 * r,
        out_res: 2 * r,
        weights: u(conv),
        bias: u(bias),
        ..SrLayer::zeroed()
    };
    steps.push(Step {
        kernel: SrKernel::Conv,
        layer: conv,
        src: Slot::Act,
        dst: Slot::X,
        skip: Slot::Empty,
        workgroups: [(2 * r * r).div_ceil(WORKGROUP), groups(c)],
    });
    let rgb = SrLayer {
        in_channels: u(c),
        out_channels: 3,
        in_res: r,
        out_res: 2 * r,
        weights: u(rgb),
        bias: u(rgb_bias),
        skip_channels: u(slots.skip_channels),
        first_channel: 0,
    };
    steps.push(Step {
        kernel: SrKernel::Rgb,
        layer: rgb,
        src: Slot::X,
        dst: slots.image,
        skip: slots.skip,
        workgroups: [pixels(2 * r), 1],
    });
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
