//! A folded network resident on a device: its frames (one batch's buffers), the recording of its
//! dispatches, and `apply` (upload, run, read back).

use std::sync::{Arc, Mutex};

use wgpu::util::DeviceExt;

use super::layers::{self, BlockPlan};
use super::{SuperresKernels, SuperresWeights, GROUP, SR_BIND_GROUP, WORKGROUP};
use crate::device::GpuContext;
use crate::error::{Error, Result};

/// The buffers of one batch of `images` feature images (`SuperRes::frame`): three scratch
/// activations (a block's features, the transposed convolution's output, its filtered form) and
/// two images, ping-ponged from block to block.
pub struct SuperresFrame {
    images: usize,
    scratch: [wgpu::Buffer; 3],
    image: [wgpu::Buffer; 2],
    /// The last block's image.
    last: usize,
    bytes: u64,
}

impl SuperresFrame {
    /// The output images (images, 3, R_out, R_out) float32, once the recorded work has run.
    pub fn output(&self) -> &wgpu::Buffer {
        &self.image[self.last]
    }

    /// Images the frame holds.
    pub fn images(&self) -> usize {
        self.images
    }

    /// Device bytes of its buffers.
    pub fn device_bytes(&self) -> u64 {
        self.bytes
    }
}

/// A folded super-resolution network resident on a device.
pub struct SuperRes {
    queue: wgpu::Queue,
    kernels: Arc<SuperresKernels>,
    weights: wgpu::Buffer,
    blocks: Vec<BlockPlan>,
    in_channels: usize,
    input_resolution: usize,
    output_resolution: usize,
    /// Floats per image of each scratch activation (`scratch_floats`).
    scratch_floats: usize,
    max_binding: u64,
}

impl SuperRes {
    /// Validates `weights` and uploads them, padded into the kernels' layout, on `ctx`'s device
    /// (the one `kernels` were built on).
    pub fn new(
        ctx: &GpuContext,
        kernels: Arc<SuperresKernels>,
        weights: &SuperresWeights,
    ) -> Result<SuperRes> {
        weights.validate()?;
        let device = &kernels.device;
        let (packed, plans, floats) = layers::plan(device, weights);
        let limit = ctx.limits.max_storage_buffer_binding_size.min(ctx.limits.max_buffer_size);
        let weight_bytes = (packed.len() * 16) as u64;
        if weight_bytes > limit {
            return Err(Error::invalid(
                "superres",
                format!("its weights take {weight_bytes} bytes, more than this device binds ({limit})"),
            ));
        }
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let buffer = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lp3d superres weights"),
            contents: bytemuck::cast_slice(&packed),
            usage: wgpu::BufferUsages::STORAGE,
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(Error::Gpu(format!("uploading the super-resolution weights failed: {e}")));
        }
        Ok(SuperRes {
            queue: ctx.queue.clone(),
            kernels,
            weights: buffer,
            blocks: plans,
            in_channels: weights.in_channels,
            input_resolution: weights.input_resolution,
            output_resolution: weights.output_resolution(),
            scratch_floats: floats,
            max_binding: limit,
        })
    }

    pub fn in_channels(&self) -> usize {
        self.in_channels
    }

    /// The device the network lives on.
    pub fn device(&self) -> &wgpu::Device {
        &self.kernels.device
    }

    pub fn input_resolution(&self) -> usize {
        self.input_resolution
    }

    pub fn output_resolution(&self) -> usize {
        self.output_resolution
    }

    /// Floats per image of a scratch activation and of an image.
    fn per_image(&self) -> (usize, usize) {
        (self.scratch_floats, 3 * self.output_resolution * self.output_resolution)
    }

    /// Most images one frame may hold on this device (at least 1 when the network fits).
    pub fn max_images_per_frame(&self) -> usize {
        let (act, img) = self.per_image();
        let per = (act.max(img).max(self.in_channels * self.input_resolution.pow(2)) * 4) as u64;
        ((self.max_binding / per.max(1)) as usize).min(65535)
    }

    /// Buffers for `images` images (1..=`max_images_per_frame`).
    pub fn frame(&self, images: usize) -> Result<SuperresFrame> {
        let most = self.max_images_per_frame();
        if most == 0 {
            let (act, img) = self.per_image();
            return Err(Error::invalid(
                "superres",
                format!(
                    "one image needs buffers of {} bytes, more than this device binds ({} bytes)",
                    act.max(img) * 4,
                    self.max_binding
                ),
            ));
        }
        if images == 0 || images > most {
            return Err(Error::invalid(
                "images",
                format!(
                    "a super-resolution frame holds 1 to {most} images on this device, asked for {images}"
                ),
            ));
        }
        let device = &self.kernels.device;
        let (act, img) = self.per_image();
        let scope = device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let make = |label: &str, floats: usize, extra: wgpu::BufferUsages| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: (floats.max(1) * images * 4) as u64,
                usage: wgpu::BufferUsages::STORAGE | extra,
                mapped_at_creation: false,
            })
        };
        let copy = wgpu::BufferUsages::COPY_SRC;
        let scratch = [
            make("lp3d superres features", act, copy),
            make("lp3d superres transposed", act, copy),
            make("lp3d superres filtered", act, copy),
        ];
        let image = [make("lp3d superres image a", img, copy), make("lp3d superres image b", img, copy)];
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(Error::Gpu(format!("out of device memory for {images} super-resolved images: {e}")));
        }
        let bytes = scratch.iter().chain(&image).map(|b| b.size()).sum();
        Ok(SuperresFrame { images, scratch, image, last: (self.blocks.len() - 1) % 2, bytes })
    }

    /// Records the network into `encoder`: `features` holds `frame.images()` feature images
    /// (images, in_channels, R, R) float32 from its start (any storage buffer, such as a
    /// render's features); the images land in `frame.output()`.
    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, features: &wgpu::Buffer, frame: &SuperresFrame) {
        let k = &self.kernels;
        let device = &k.device;
        let images = frame.images as u32;
        let group = |uniform: &wgpu::Buffer, src: &wgpu::Buffer, dst: &wgpu::Buffer, skip: &wgpu::Buffer| {
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("lp3d superres layer bindings"),
                layout: &k.layout,
                entries: &[
                    wgpu::BindGroupEntry { binding: 0, resource: uniform.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 1, resource: self.weights.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 2, resource: src.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 3, resource: dst.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 4, resource: skip.as_entire_binding() },
                ],
            })
        };
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("lp3d superres pass"),
            timestamp_writes: None,
        });
        let [x, up, act] = &frame.scratch;
        for (i, b) in self.blocks.iter().enumerate() {
            // x_in -> (conv_up) -> up -> (fir) -> act, by chunks of channels; act -> (conv) -> x,
            // which the next block reads (x_in is dead once every chunk has read it).
            let x_in = if i == 0 { features } else { x };
            let skip = if i == 0 { features } else { &frame.image[(i + 1) % 2] };
            let r = b.res as u32;
            let groups = |c: usize| (c as u32).div_ceil(GROUP as u32);
            let pixels = |side: u32| (side * side).div_ceil(WORKGROUP);
            let mut steps: Vec<(&wgpu::ComputePipeline, wgpu::BindGroup, [u32; 3])> = Vec::new();
            for (n, conv_up, fir) in &b.chunks {
                steps.push((
                    &k.conv_up,
                    group(conv_up, x_in, up, &k.placeholder),
                    [pixels(r + 1), groups(*n), images],
                ));
                steps.push((
                    &k.fir_act,
                    group(fir, up, act, &k.placeholder),
                    [pixels(2 * r), *n as u32, images],
                ));
            }
            steps.push((
                &k.conv,
                group(&b.conv, act, x, &k.placeholder),
                [(2 * r * r).div_ceil(WORKGROUP), groups(b.channels), images],
            ));
            steps.push((&k.rgb, group(&b.rgb, x, &frame.image[i % 2], skip), [pixels(2 * r), 1, images]));
            for (pipeline, bind, [gx, gy, gz]) in &steps {
                pass.set_pipeline(pipeline);
                pass.set_bind_group(SR_BIND_GROUP, bind, &[]);
                pass.dispatch_workgroups(*gx, *gy, *gz);
            }
        }
    }

    /// Super-resolves `n_images` feature images (n_images, in_channels, R, R) float32 row-major
    /// (R = `input_resolution`) and reads the images (n_images, 3, R_out, R_out) back. Batches
    /// larger than a frame run in chunks.
    pub fn apply(&self, features: &[f32], n_images: usize) -> Result<Vec<f32>> {
        let per_in = self.in_channels * self.input_resolution * self.input_resolution;
        let r = self.input_resolution;
        if n_images == 0 || features.len() != n_images * per_in {
            return Err(Error::invalid(
                "features",
                format!(
                    "expected ({n_images}, {}, {r}, {r}) = {} values, got {}",
                    self.in_channels,
                    n_images * per_in,
                    features.len()
                ),
            ));
        }
        if let Some(i) = features.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid("features", format!("contains NaN/Inf at flat index {i}")));
        }
        let device = &self.kernels.device;
        let chunk = n_images.min(self.max_images_per_frame());
        let frame = self.frame(chunk)?;
        let per_out = 3 * self.output_resolution * self.output_resolution;
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let input = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("lp3d superres features"),
            size: (chunk * per_in * 4) as u64,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let readback = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("lp3d superres readback"),
            size: (chunk * per_out * 4) as u64,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut out = vec![0f32; n_images * per_out];
        for first in (0..n_images).step_by(chunk) {
            let count = chunk.min(n_images - first);
            self.queue.write_buffer(
                &input,
                0,
                bytemuck::cast_slice(&features[first * per_in..(first + count) * per_in]),
            );
            let mut encoder = device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("lp3d superres") });
            // A short last chunk still runs the frame's full count: the extra images read stale
            // inputs and are not copied out.
            self.record(&mut encoder, &input, &frame);
            let bytes = (count * per_out * 4) as u64;
            encoder.copy_buffer_to_buffer(frame.output(), 0, &readback, 0, bytes);
            self.queue.submit([encoder.finish()]);
            read_back(device, &readback, bytes, &mut out[first * per_out..(first + count) * per_out])?;
        }
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(Error::Gpu(format!("the super-resolution dispatch failed: {e}")));
        }
        if let Some(i) = out.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(
                "superres",
                format!(
                    "the network overflowed float32 on image {} (its weights or the features are too large)",
                    i / per_out
                ),
            ));
        }
        Ok(out)
    }
}

fn read_back(device: &wgpu::Device, buf: &wgpu::Buffer, bytes: u64, dst: &mut [f32]) -> Result<()> {
    let status = Arc::new(Mutex::new(None));
    let sink = status.clone();
    buf.map_async(wgpu::MapMode::Read, 0..bytes, move |r| {
        if let Ok(mut s) = sink.lock() {
            *s = Some(r.map_err(|e| e.to_string()));
        }
    });
    device
        .poll(wgpu::PollType::wait_indefinitely())
        .map_err(|e| Error::Gpu(format!("waiting for the GPU failed: {e}")))?;
    if let Some(Err(e)) = status.lock().ok().and_then(|s| s.clone()) {
        return Err(Error::Gpu(format!("reading the super-resolved images back failed: {e}")));
    }
    {
        let view =
            buf.get_mapped_range(0..bytes).map_err(|e| Error::Gpu(format!("mapping results failed: {e}")))?;
        dst.copy_from_slice(bytemuck::cast_slice(&view));
    }
    buf.unmap();
    Ok(())
}
