//! A folded network resident on a device: its frames (one batch's buffers), the recording of its
//! dispatches, and `apply` (upload, run, read back).

use std::sync::{Arc, Mutex};

use wgpu::util::DeviceExt;

use super::layers::{self, NetworkPlan, Slot, SrKernel};
use super::{SuperresKernels, SuperresWeights, SR_BIND_GROUP};
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
    last: Slot,
    bytes: u64,
}

impl SuperresFrame {
    /// The output images (images, 3, R_out, R_out) float32, once the recorded work has run.
    pub fn output(&self) -> &wgpu::Buffer {
        self.slot(self.last).expect("the output is one of the frame's images")
    }

    /// The frame's buffer of `slot` (None for the network's input and for no buffer).
    fn slot(&self, slot: Slot) -> Option<&wgpu::Buffer> {
        match slot {
            Slot::X => Some(&self.scratch[0]),
            Slot::Up => Some(&self.scratch[1]),
            Slot::Act => Some(&self.scratch[2]),
            Slot::ImageA => Some(&self.image[0]),
            Slot::ImageB => Some(&self.image[1]),
            Slot::Features | Slot::Empty => None,
        }
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
    plan: NetworkPlan,
    /// Each step's layer uniform, in the plan's order.
    uniforms: Vec<wgpu::Buffer>,
    in_channels: usize,
    input_resolution: usize,
    output_resolution: usize,
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
        let plan = layers::plan(weights);
        let packed = &plan.packed;
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
            contents: bytemuck::cast_slice(packed),
            usage: wgpu::BufferUsages::STORAGE,
        });
        let uniforms = plan
            .steps
            .iter()
            .map(|step| {
                device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("lp3d superres layer"),
                    contents: bytemuck::bytes_of(&step.layer),
                    usage: wgpu::BufferUsages::UNIFORM,
                })
            })
            .collect();
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(Error::Gpu(format!("uploading the super-resolution weights failed: {e}")));
        }
        Ok(SuperRes {
            queue: ctx.queue.clone(),
            kernels,
            weights: buffer,
            plan,
            uniforms,
            in_channels: weights.in_channels,
            input_resolution: weights.input_resolution,
            output_resolution: weights.output_resolution(),
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
        (self.plan.scratch_floats, self.plan.image_floats)
    }

    /// The network's packed weights and dispatches, for a runner of its own (the web page's).
    pub fn plan(&self) -> &NetworkPlan {
        &self.plan
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
        Ok(SuperresFrame { images, scratch, image, last: self.plan.output, bytes })
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
        let bound = |slot: Slot| match slot {
            Slot::Features => features,
            Slot::Empty => &k.placeholder,
            s => frame.slot(s).expect("a frame buffer"),
        };
        for (step, uniform) in self.plan.steps.iter().zip(&self.uniforms) {
            let pipeline = match step.kernel {
                SrKernel::ConvUp => &k.conv_up,
                SrKernel::FirAct => &k.fir_act,
                SrKernel::Conv => &k.conv,
                SrKernel::Rgb => &k.rgb,
            };
            let bind = group(uniform, bound(step.src), bound(step.dst), bound(step.skip));
            pass.set_pipeline(pipeline);
            pass.set_bind_group(SR_BIND_GROUP, &bind, &[]);
            pass.dispatch_workgroups(step.workgroups[0], step.workgroups[1], images);
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
