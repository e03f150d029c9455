//! GPU pipelines and dispatch. The CPU validates and prepares buffers; all rendering work
//! happens in the WGSL kernels of `shaders/` (one ray per invocation).

use std::sync::{Arc, Mutex};

use wgpu::util::DeviceExt;

use crate::camera::Camera;
use crate::device::GpuContext;
use crate::error::{Error, Result};
use crate::gpu_types::{DecoderUniform, Params};
use crate::settings::{Outputs, RenderSettings};
use crate::shaders;
use crate::triplane::{SceneInfo, Triplane};

const WORKGROUP: u32 = 64;
/// Most cameras per call (one dispatch row each).
pub const MAX_CAMERAS: usize = 65535;

/// A triplane resident on the GPU: planes channel-last plus the decoder uniform.
pub struct GpuTriplane {
    planes: wgpu::Buffer,
    decoder: wgpu::Buffer,
    scene: SceneInfo,
}

impl GpuTriplane {
    pub fn scene(&self) -> SceneInfo {
        self.scene
    }
}

/// Render results, float32, row-major: `features` (B, 32, R, R), `rgb` (B, 3, R, R),
/// `depth` and `weights_sum` (B, R, R). Only requested outputs are present.
#[derive(Debug, Clone, Default)]
pub struct RenderOutput {
    pub n_cameras: usize,
    pub resolution: usize,
    pub features: Option<Vec<f32>>,
    pub rgb: Option<Vec<f32>>,
    pub depth: Option<Vec<f32>>,
    pub weights_sum: Option<Vec<f32>>,
}

pub struct Renderer {
    device: wgpu::Device,
    queue: wgpu::Queue,
    limits: wgpu::Limits,
    layout: wgpu::BindGroupLayout,
    render_pipeline: wgpu::ComputePipeline,
    bounds_pipeline: wgpu::ComputePipeline,
    /// Errors wgpu reports outside an error scope, kept instead of panicking.
    uncaptured: Arc<Mutex<Option<String>>>,
}

fn storage_entry(binding: u32, read_only: bool) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

fn uniform_entry(binding: u32) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

impl Renderer {
    /// Builds the pipelines on `ctx`'s device (a first dispatch may JIT-compile them).
    pub fn new(ctx: &GpuContext) -> Result<Renderer> {
        let device = ctx.device.clone();
        let uncaptured = Arc::new(Mutex::new(None));
        {
            let sink = uncaptured.clone();
            device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
                if let Ok(mut slot) = sink.lock() {
                    slot.get_or_insert_with(|| e.to_string());
                }
            }));
        }
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("lp3d render module"),
            source: wgpu::ShaderSource::Wgsl(shaders::render_module_source().into()),
        });
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("lp3d render bindings"),
            entries: &[
                uniform_entry(0),
                storage_entry(1, true),
                storage_entry(2, true),
                uniform_entry(3),
                storage_entry(4, false),
                storage_entry(5, false),
                storage_entry(6, false),
                storage_entry(7, false),
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("lp3d render pipeline layout"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let make = |entry: &str, label: &str| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(label),
                layout: Some(&pipeline_layout),
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let render_pipeline = make(shaders::RENDER_ENTRY, "lp3d render_rays");
        let bounds_pipeline = make(shaders::DEPTH_BOUNDS_ENTRY, "lp3d depth_bounds_pass");
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(Error::Gpu(format!("building the render pipelines failed: {e}")));
        }
        Ok(Renderer {
            device,
            queue: ctx.queue.clone(),
            limits: ctx.limits.clone(),
            layout,
            render_pipeline,
            bounds_pipeline,
            uncaptured,
        })
    }

    /// Uploads a validated triplane.
    pub fn upload(&self, tri: &Triplane) -> Result<GpuTriplane> {
        tri.validate()?;
        let planes = tri.planes_channel_last();
        let bytes = (planes.len() * 4) as u64;
        let max = self.limits.max_storage_buffer_binding_size.min(self.limits.max_buffer_size);
        if bytes > max {
            return Err(Error::invalid(
                "planes",
                format!(
                    "{} MiB exceeds this device's storage buffer limit of {} MiB",
                    bytes >> 20,
                    max >> 20
                ),
            ));
        }
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let planes = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lp3d planes (3, H, W, 32)"),
            contents: bytemuck::cast_slice(&planes),
            usage: wgpu::BufferUsages::STORAGE,
        });
        let decoder = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lp3d decoder weights"),
            contents: bytemuck::bytes_of(&DecoderUniform::from_decoder(&tri.decoder)),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(Error::Gpu(format!("uploading the triplane failed: {e}")));
        }
        Ok(GpuTriplane { planes, decoder, scene: tri.scene() })
    }

    /// Renders `cameras` (one image each) of an uploaded triplane.
    pub fn render(
        &self,
        tri: &GpuTriplane,
        cameras: &[Camera],
        settings: &RenderSettings,
        outputs: Outputs,
    ) -> Result<RenderOutput> {
        settings.validate()?;
        if cameras.is_empty() || cameras.len() > MAX_CAMERAS {
            return Err(Error::invalid(
                "camera",
                format!("batch size must be in [1, {MAX_CAMERAS}], got {}", cameras.len()),
            ));
        }
        let n_cam = cameras.len();
        let r = settings.resolution as usize;
        let n_pix = r * r;
        let fc = outputs.feature_channels() as usize;
        let mut params = Params::new(&tri.scene, settings, fc as u32, n_cam as u32);

        // Split the batch so each dispatch's output fits one storage binding.
        let max_binding =
            self.limits.max_storage_buffer_binding_size.min(self.limits.max_buffer_size) as usize;
        let per_cam = (fc.max(1) * n_pix * 4).max(1);
        let chunk = (max_binding / per_cam).clamp(1, n_cam);
        if per_cam > max_binding {
            return Err(Error::invalid(
                "resolution",
                format!("one image's outputs ({} MiB) exceed the device's buffer limit", per_cam >> 20),
            ));
        }

        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let oom_scope = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let dev = &self.device;
        let storage = |label: &str, size: usize| {
            dev.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: (size.max(1) * 4) as u64,
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_SRC
                    | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        let readback = |label: &str, size: usize| {
            dev.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: (size.max(1) * 4) as u64,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        let labels: Vec<f32> = cameras.iter().flat_map(|c| c.0).collect();
        let camera_buf = dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lp3d cameras (B, 25)"),
            contents: bytemuck::cast_slice(&labels),
            usage: wgpu::BufferUsages::STORAGE,
        });
        let params_buf = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("lp3d params"),
            size: std::mem::size_of::<Params>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let bounds_buf = dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lp3d depth bounds"),
            contents: bytemuck::cast_slice(&[f32::INFINITY.to_bits(), 0u32]),
            usage: wgpu::BufferUsages::STORAGE,
        });
        let feat_buf = storage("lp3d features out", chunk * fc * n_pix);
        let depth_buf = storage("lp3d depth out", chunk * n_pix);
        let wsum_buf = storage("lp3d weights_sum out", chunk * n_pix);
        let feat_read = readback("lp3d features readback", chunk * fc * n_pix);
        let depth_read = readback("lp3d depth readback", chunk * n_pix);
        let wsum_read = readback("lp3d weights_sum readback", chunk * n_pix);
        let bind_group = dev.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("lp3d render bind group"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: params_buf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: camera_buf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 2, resource: tri.planes.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 3, resource: tri.decoder.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 4, resource: feat_buf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 5, resource: depth_buf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 6, resource: wsum_buf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 7, resource: bounds_buf.as_entire_binding() },
            ],
        });
        if let Some(e) = pollster::block_on(oom_scope.pop()) {
            drop(scope);
            return Err(Error::Gpu(format!("out of device memory allocating render buffers: {e}")));
        }

        let groups_x = (n_pix as u32).div_ceil(WORKGROUP);
        let mut features = vec![0f32; if outputs.features || outputs.rgb { n_cam * fc * n_pix } else { 0 }];
        let mut depth = vec![0f32; n_cam * n_pix];
        let mut weights_sum = vec![0f32; n_cam * n_pix];
        let mut first = 0usize;
        while first < n_cam {
            let count = chunk.min(n_cam - first);
            params.camera_offset = first as u32;
            self.queue.write_buffer(&params_buf, 0, bytemuck::bytes_of(&params));
            let mut encoder =
                dev.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("lp3d render") });
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("lp3d render pass"),
                    timestamp_writes: None,
                });
                pass.set_bind_group(0, &bind_group, &[]);
                if first == 0 {
                    // Batch-global depth range first: render_rays clamps against it.
                    pass.set_pipeline(&self.bounds_pipeline);
                    pass.dispatch_workgroups(groups_x, n_cam as u32, 1);
                }
                pass.set_pipeline(&self.render_pipeline);
                pass.dispatch_workgroups(groups_x, count as u32, 1);
            }
            let fbytes = (count * fc * n_pix * 4) as u64;
            let pbytes = (count * n_pix * 4) as u64;
            if fc > 0 {
                encoder.copy_buffer_to_buffer(&feat_buf, 0, &feat_read, 0, fbytes);
            }
            encoder.copy_buffer_to_buffer(&depth_buf, 0, &depth_read, 0, pbytes);
            encoder.copy_buffer_to_buffer(&wsum_buf, 0, &wsum_read, 0, pbytes);
            self.queue.submit([encoder.finish()]);
            let mut jobs: Vec<(&wgpu::Buffer, u64, &mut [f32])> = vec![
                (&depth_read, pbytes, &mut depth[first * n_pix..(first + count) * n_pix]),
                (&wsum_read, pbytes, &mut weights_sum[first * n_pix..(first + count) * n_pix]),
            ];
            if fc > 0 {
                jobs.push((
                    &feat_read,
                    fbytes,
                    &mut features[first * fc * n_pix..(first + count) * fc * n_pix],
                ));
            }
            self.read_back(&mut jobs)?;
            first += count;
        }
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(Error::Gpu(format!("render dispatch failed: {e}")));
        }
        if let Some(e) = self.uncaptured.lock().ok().and_then(|mut s| s.take()) {
            return Err(Error::Gpu(e));
        }

        let mut out = RenderOutput { n_cameras: n_cam, resolution: r, ..Default::default() };
        if outputs.rgb {
            let rgb = if fc == 3 {
                features.clone()
            } else {
                // First three of the 32 channels of each image.
                features.chunks(fc * n_pix).flat_map(|img| img[..3 * n_pix].iter().copied()).collect()
            };
            out.rgb = Some(rgb);
        }
        if outputs.features {
            out.features = Some(features);
        }
        if outputs.depth {
            out.depth = Some(depth);
        }
        if outputs.weights_sum {
            out.weights_sum = Some(weights_sum);
        }
        Ok(out)
    }

    /// Maps readback buffers and copies `bytes` of each into its destination.
    fn read_back(&self, jobs: &mut [(&wgpu::Buffer, u64, &mut [f32])]) -> Result<()> {
        let status = Arc::new(Mutex::new(Vec::new()));
        for (buf, bytes, _) in jobs.iter() {
            let status = status.clone();
            buf.map_async(wgpu::MapMode::Read, 0..*bytes, move |r| {
                if let Ok(mut s) = status.lock() {
                    s.push(r.map_err(|e| e.to_string()));
                }
            });
        }
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| Error::Gpu(format!("waiting for the GPU failed: {e}")))?;
        if let Some(Err(e)) = status.lock().ok().and_then(|s| s.iter().find(|r| r.is_err()).cloned()) {
            return Err(Error::Gpu(format!("reading results back failed: {e}")));
        }
        for (buf, bytes, dst) in jobs.iter_mut() {
            {
                let view = buf
                    .get_mapped_range(0..*bytes)
                    .map_err(|e| Error::Gpu(format!("mapping results failed: {e}")))?;
                dst.copy_from_slice(bytemuck::cast_slice(&view));
            }
            buf.unmap();
        }
        Ok(())
    }
}
