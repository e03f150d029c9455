//! EG3D's super-resolution network on the GPU, after the volume render and on the same device:
//! the folded form of `lp3d.nets.superres` (`FoldedSuperResolution`: its constant w folded into
//! every weight, so each layer is a plain convolution), run by the four kernels of
//! `shaders/superres.wgsl`. [`SuperresWeights`] holds a network's weights under the names the
//! Python module gives them and checks them (and reads them from a model package's
//! `MODEL.superres.npz`, `superres/file.rs`); [`SuperresKernels`] are the pipelines, built once per
//! device and shared; [`SuperRes`] is one network resident on the device, which turns feature
//! images (B, C, R, R) into images (B, 3, R·2^blocks, R·2^blocks), batched.
//!
//! Each ×2 block is four dispatches, in one command stream: `sr_conv_up` (the transposed
//! convolution), `sr_fir_act` (its FIR filter, bias, lrelu), `sr_conv` (the 3x3 convolution, bias,
//! lrelu) and `sr_rgb` (the image skip upsampled, plus ToRGB). [`SuperRes::record`] records them
//! into a caller's encoder reading any feature buffer of that layout, such as a render's.

mod file;
mod kernels;
mod layers;
mod network;

use bytemuck::{Pod, Zeroable};

use crate::error::{Error, Result};

pub use file::{WEIGHTS_FORMAT_VERSION, WEIGHTS_PARTS};
pub use kernels::SuperresKernels;
pub use layers::{NetworkPlan, Slot, SrKernel, Step};
pub use network::{SuperRes, SuperresFrame};

/// Most channels of the feature image (`SUPERRES_CAPS` in `lp3d.nets.superres`).
pub const MAX_IN_CHANNELS: usize = 256;
/// Most channels of one block (`MAX_SUPERRES_WIDTH` there).
pub const MAX_WIDTH: usize = 4096;
/// Largest output side: one dispatch row of 64-wide workgroups covers its pixels
/// (1024² / 64 = 16384 workgroups, under wgpu's 65535 per dimension).
pub const MAX_OUTPUT_RESOLUTION: usize = 1024;
/// Output channels per invocation of the convolutions (`SR_GROUP` in the WGSL); weights are
/// padded to a multiple of it.
const GROUP: usize = 8;
const WORKGROUP: u32 = 64;
/// The bind group `shaders/superres.wgsl` declares its bindings in.
const SR_BIND_GROUP: u32 = 2;

/// One ×2 block of the folded network, under `FoldedSuperResolution`'s names (one tensor per
/// block each there: `convs_up[i]` is this block's `conv_up`), row-major float32.
#[derive(Debug, Clone, PartialEq)]
pub struct SuperresBlock {
    /// The block's width c.
    pub channels: usize,
    /// (c, c_in, 3, 3): the stride-2 transposed convolution's weight as `convs_up` holds it
    /// (torch's `conv_transpose2d` takes it transposed to (c_in, c, 3, 3)).
    pub conv_up: Vec<f32>,
    /// (c,), added after the FIR filter that follows the transposed convolution.
    pub bias_up: Vec<f32>,
    /// (c, c, 3, 3), padding 1.
    pub conv: Vec<f32>,
    /// (c,).
    pub bias: Vec<f32>,
    /// (3, c, 1, 1): ToRGB.
    pub rgb_weight: Vec<f32>,
    /// (3,).
    pub rgb_bias: Vec<f32>,
}

/// A folded super-resolution network: feature images of `in_channels` at `input_resolution`²
/// (rgb = the first 3 channels), then one block per doubling.
#[derive(Debug, Clone, PartialEq)]
pub struct SuperresWeights {
    pub in_channels: usize,
    pub input_resolution: usize,
    pub blocks: Vec<SuperresBlock>,
}

impl SuperresWeights {
    /// The output side: `input_resolution · 2^blocks`.
    pub fn output_resolution(&self) -> usize {
        self.input_resolution << self.blocks.len().min(usize::BITS as usize - 1)
    }

    /// Checks sizes, caps and values; an error names the field as `FoldedSuperResolution` does
    /// (`convs_up[1]`, `rgb_biases[0]`, ...).
    pub fn validate(&self) -> Result<()> {
        let c_in = self.in_channels;
        if !(3..=MAX_IN_CHANNELS).contains(&c_in) {
            return Err(Error::invalid(
                "in_channels",
                format!("must be in [3, {MAX_IN_CHANNELS}] (rgb is the first 3), got {c_in}"),
            ));
        }
        if self.blocks.is_empty() || self.blocks.len() > 10 {
            return Err(Error::invalid(
                "blocks",
                format!("need 1 to 10 ×2 blocks, got {}", self.blocks.len()),
            ));
        }
        let r = self.input_resolution;
        if r == 0 || r.checked_shl(self.blocks.len() as u32).is_none_or(|o| o > MAX_OUTPUT_RESOLUTION) {
            return Err(Error::invalid(
                "input_resolution",
                format!(
                    "{r} with {} blocks: the output side must be in [2, {MAX_OUTPUT_RESOLUTION}]",
                    self.blocks.len()
                ),
            ));
        }
        let mut cin = c_in;
        for (i, b) in self.blocks.iter().enumerate() {
            let c = b.channels;
            if !(1..=MAX_WIDTH).contains(&c) {
                return Err(Error::invalid(
                    format!("convs_up[{i}]"),
                    format!("the block's width must be in [1, {MAX_WIDTH}], got {c}"),
                ));
            }
            let parts: [(&str, &[f32], Vec<usize>); 6] = [
                ("convs_up", &b.conv_up, vec![c, cin, 3, 3]),
                ("biases_up", &b.bias_up, vec![c]),
                ("convs", &b.conv, vec![c, c, 3, 3]),
                ("biases", &b.bias, vec![c]),
                ("rgb_weights", &b.rgb_weight, vec![3, c, 1, 1]),
                ("rgb_biases", &b.rgb_bias, vec![3]),
            ];
            for (name, values, shape) in parts {
                let n: usize = shape.iter().product();
                if values.len() != n {
                    return Err(Error::invalid(
                        format!("{name}[{i}]"),
                        format!("expected shape {shape:?} ({n} values), got {} values", values.len()),
                    ));
                }
                if let Some(j) = values.iter().position(|v| !v.is_finite()) {
                    return Err(Error::invalid(
                        format!("{name}[{i}]"),
                        format!("contains NaN/Inf at flat index {j}"),
                    ));
                }
            }
            cin = c;
        }
        Ok(())
    }
}

/// Mirrors `struct SrLayer` in `shaders/superres.wgsl` (a test checks the size with naga).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct SrLayer {
    pub in_channels: u32,
    pub out_channels: u32,
    pub in_res: u32,
    pub out_res: u32,
    pub weights: u32,
    pub bias: u32,
    pub skip_channels: u32,
    pub first_channel: u32,
}
