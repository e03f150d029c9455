//! GPU pipelines and dispatch. The CPU validates and prepares buffers; all rendering work
//! happens in the WGSL kernels of `shaders/` (one ray per invocation). Uploading a triplane is
//! `renderer/upload.rs`, one request's buffers and dispatches `renderer/frame.rs`.

mod background;
mod baking;
mod fine_bricks;
mod frame;
mod layouts;
mod saved_field;
mod superres_chain;
mod upload;

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::thread::JoinHandle;

use wgpu::util::DeviceExt;

use crate::camera::Camera;
use crate::device::GpuContext;
use crate::error::{Error, Result};
use crate::gpu_types::{DecoderUniform, DisplayUniform, Params, FLAG_HALF_PLANES, FLAG_JITTER};
use crate::kernel::{build_render_pipeline, fast_kernel_marker, Kernel, KernelChoice};
use crate::occupancy::Occupancy;
use crate::settings::{Display, Outputs, RenderSettings};
use crate::shaders;
use crate::superres::SuperRes;
use crate::triplane::{PlaneDtype, SceneInfo, Triplane, N_CHANNELS};
use background::spawn_fast_kernel_compile;
use layouts::Layouts;

pub use baking::{GpuBaked, BAKE_CHUNK};

const WORKGROUP: u32 = 64;
/// Texel format of `render_to_texture` targets (an sRGB-unaware 8-bit RGBA storage texture).
pub const DISPLAY_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
/// Most cameras per call (one dispatch row each).
pub const MAX_CAMERAS: usize = 65535;

/// A triplane resident on the GPU: planes channel-last plus the decoder uniform, and the
/// occupancy grid when it has one.
pub struct GpuTriplane {
    planes: wgpu::Buffer,
    decoder: wgpu::Buffer,
    scene: SceneInfo,
    /// Planes stored as packed float16 pairs: the triplane's planes were float16, so this is
    /// lossless and halves the plane memory and its traffic.
    half: bool,
    occupancy: Mutex<Option<GpuOccupancy>>,
    /// The baked field (`Renderer::bake`), made from the occupancy grid on first use.
    baked: Mutex<Option<Arc<GpuBaked>>>,
}

/// The grid (bounds on the CPU) and its bits on the GPU for the last threshold used.
struct GpuOccupancy {
    grid: Arc<Occupancy>,
    bits: Option<(f64, wgpu::Buffer)>,
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

/// Buffers and bindings of one render request (see `Renderer::prepare`).
struct Frame {
    params: Params,
    params_buf: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
    features: wgpu::Buffer,
    depth: wgpu::Buffer,
    weights_sum: wgpu::Buffer,
    n_cam: usize,
    n_pix: usize,
    /// Feature channels per image in `features` (32, 3 or 0).
    fc: usize,
    /// Cameras per dispatch.
    chunk: usize,
    /// Device bytes allocated for this frame (outputs, uniforms, cameras).
    bytes: u64,
}

pub struct Renderer {
    device: wgpu::Device,
    queue: wgpu::Queue,
    limits: wgpu::Limits,
    layout: wgpu::BindGroupLayout,
    module: wgpu::ShaderModule,
    pipeline_layout: wgpu::PipelineLayout,
    /// render_rays with the unrolled decoder, once built (at once, or after the background
    /// compile finished).
    fast_pipeline: OnceLock<wgpu::ComputePipeline>,
    /// render_rays with the rolled decoder, when the choice uses it.
    quick_pipeline: Option<wgpu::ComputePipeline>,
    /// The background compile of the fast kernel (`KernelChoice::QuickThenFast`, and `Auto` on
    /// a CPU adapter without the marker).
    background: Mutex<Option<JoinHandle<Result<()>>>>,
    /// Where to record that the fast kernel and the bake kernel with its decoder are in Mesa's
    /// shader cache (`fast_kernel_marker`), until this process has run both and done so.
    marker: Mutex<Option<std::path::PathBuf>>,
    /// Which of the two this process has run: the fast render kernel [0], the bake with the fast
    /// kernel's decoder [1].
    fast_ran: [AtomicBool; 2],
    /// Walk every sample (`set_full_walk`).
    full_walk: AtomicBool,
    bounds_pipeline: wgpu::ComputePipeline,
    present_layout: wgpu::BindGroupLayout,
    present_pipeline: wgpu::ComputePipeline,
    /// Bound in place of occupancy bits when the skip is off.
    no_occupancy: wgpu::Buffer,
    /// The baked field's pipelines (`renderer/baking.rs`).
    baked: baking::BakedPipelines,
    /// Device bytes of the last frame's own buffers, readbacks included.
    last_frame_bytes: AtomicU64,
    /// Errors wgpu reports outside an error scope, kept instead of panicking.
    uncaptured: Arc<Mutex<Option<String>>>,
}

impl Renderer {
    /// Builds the pipelines on `ctx`'s device (a first dispatch may JIT-compile them), with
    /// the kernels `LP3D_KERNEL` asks for (`KernelChoice::from_env`, default `Auto`).
    pub fn new(ctx: &GpuContext) -> Result<Renderer> {
        let full_walk = frame::full_walk_from_env()?;
        let renderer = Renderer::with_kernel(ctx, KernelChoice::from_env()?)?;
        renderer.set_full_walk(full_walk);
        Ok(renderer)
    }

    /// Builds the pipelines with an explicit kernel choice.
    pub fn with_kernel(ctx: &GpuContext, choice: KernelChoice) -> Result<Renderer> {
        let device = ctx.device.clone();
        let uncaptured = keep_first_uncaptured_error(&device);
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("lp3d render module"),
            source: wgpu::ShaderSource::Wgsl(shaders::render_module_source().into()),
        });
        let Layouts {
            render: layout,
            render_pipeline_layout: pipeline_layout,
            present: present_layout,
            present_pipeline_layout,
            bake: bake_layout,
            bake_pipeline_layout,
        } = Layouts::new(&device);
        let make = |entry: &str, label: &str, layout: &wgpu::PipelineLayout| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(label),
                layout: Some(layout),
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let marker = fast_kernel_marker(&ctx.adapter_info);
        let background_compile = choice.compiles_in_background(&ctx.adapter_info, marker.as_deref());
        let fast_pipeline = OnceLock::new();
        let quick_pipeline = match choice {
            KernelChoice::Quick => {
                Some(build_render_pipeline(&device, &module, &pipeline_layout, Kernel::Quick))
            }
            _ if background_compile => {
                Some(build_render_pipeline(&device, &module, &pipeline_layout, Kernel::Quick))
            }
            _ => {
                let _ = fast_pipeline.set(build_render_pipeline(
                    &device,
                    &module,
                    &pipeline_layout,
                    Kernel::Fast,
                ));
                None
            }
        };
        let bounds_pipeline = make(shaders::DEPTH_BOUNDS_ENTRY, "lp3d depth_bounds_pass", &pipeline_layout);
        let present_pipeline = make(shaders::PRESENT_ENTRY, "lp3d present", &present_pipeline_layout);
        let no_occupancy = layouts::placeholder(&device, "lp3d no occupancy");
        let baked = baking::BakedPipelines::new(&device, bake_layout, bake_pipeline_layout);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(Error::Gpu(format!("building the render pipelines failed: {e}")));
        }
        let background = background_compile
            .then(|| spawn_fast_kernel_compile(ctx.adapter_info.name.clone(), marker.clone()))
            .transpose()?;
        Ok(Renderer {
            no_occupancy,
            baked,
            last_frame_bytes: AtomicU64::new(0),
            device,
            queue: ctx.queue.clone(),
            limits: ctx.limits.clone(),
            layout,
            module,
            pipeline_layout,
            fast_pipeline,
            quick_pipeline,
            background: Mutex::new(background),
            marker: Mutex::new(marker),
            fast_ran: [AtomicBool::new(false), AtomicBool::new(false)],
            full_walk: AtomicBool::new(false),
            bounds_pipeline,
            present_layout,
            present_pipeline,
            uncaptured,
        })
    }

    /// The kernel the last render used (or the next will, before any render). With a
    /// background compile (`KernelChoice::QuickThenFast`, or `Auto` on a CPU adapter the first
    /// time) this is `Quick` until a render finds that compile finished (then `Fast`; it stays
    /// `Quick` if the compile failed).
    pub fn kernel(&self) -> Kernel {
        if self.fast_pipeline.get().is_some() {
            Kernel::Fast
        } else {
            Kernel::Quick
        }
    }

    /// Blocks until the background compile of the fast kernel (if any) has finished, switches
    /// to it and returns the kernel renders use from now on (`Quick` for `KernelChoice::Quick`).
    /// An error means that compile failed; renders then keep using the quick kernel.
    pub fn wait_for_fast_kernel(&self) -> Result<Kernel> {
        let handle = self.background.lock().map_err(|_| Error::Gpu("kernel lock poisoned".into()))?.take();
        if let Some(handle) = handle {
            handle.join().map_err(|_| Error::Gpu("the background kernel compile panicked".into()))??;
            self.set_fast();
        }
        Ok(self.kernel())
    }

    /// Joins a finished background compile and switches to the fast kernel; whether it did.
    fn take_background(&self) -> bool {
        let Ok(mut slot) = self.background.lock() else { return false };
        if !slot.as_ref().is_some_and(|h| h.is_finished()) {
            return self.fast_pipeline.get().is_some();
        }
        let ok = matches!(slot.take().map(|h| h.join()), Some(Ok(Ok(()))));
        drop(slot);
        if ok {
            self.set_fast();
        }
        ok
    }

    fn set_fast(&self) {
        self.fast_pipeline.get_or_init(|| {
            build_render_pipeline(&self.device, &self.module, &self.pipeline_layout, Kernel::Fast)
        });
    }

    /// The render_rays pipeline for the next dispatch (switching to the fast kernel once its
    /// background compile has finished).
    fn render_pipeline(&self) -> &wgpu::ComputePipeline {
        if let Some(p) = self.fast_pipeline.get() {
            return p;
        }
        if self.take_background() {
            if let Some(p) = self.fast_pipeline.get() {
                return p;
            }
        }
        self.quick_pipeline.as_ref().or(self.fast_pipeline.get()).expect("a render pipeline was built")
    }

    /// Device bytes of the last rendered frame's own buffers (outputs, readbacks, uniforms,
    /// cameras), excluding the triplane's (`GpuTriplane::device_bytes`).
    pub fn last_frame_device_bytes(&self) -> u64 {
        self.last_frame_bytes.load(Ordering::Relaxed)
    }

    /// Renders `cameras` (one image each) of an uploaded triplane and reads the results back.
    pub fn render(
        &self,
        tri: &GpuTriplane,
        cameras: &[Camera],
        settings: &RenderSettings,
        outputs: Outputs,
    ) -> Result<RenderOutput> {
        Ok(self.render_with_superres(tri, cameras, settings, outputs, None)?.0)
    }

    /// [`Renderer::render`], and with `superres` the feature images super-resolved in the same
    /// command buffers (no round trip through the host): the images (B, 3, R_out, R_out) come
    /// back beside `outputs`. The network must live on this renderer's device and take the
    /// render's resolution and its 32 feature channels.
    // Long because: the chunk loop dispatches, copies and reads back each chunk before the next
    // reuses the frame's buffers; its steps share those buffers and the running offsets.
    pub fn render_with_superres(
        &self,
        tri: &GpuTriplane,
        cameras: &[Camera],
        settings: &RenderSettings,
        outputs: Outputs,
        superres: Option<&SuperRes>,
    ) -> Result<(RenderOutput, Option<Vec<f32>>)> {
        if let Some(sr) = superres {
            superres_chain::check(self, sr, settings)?;
        }
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        // The network reads the 32-channel feature image, asked for or not.
        let computed = if superres.is_some() { Outputs { features: true, ..outputs } } else { outputs };
        let mut frame = self.prepare(tri, cameras, settings, computed)?;
        let (n_cam, n_pix, fc) = (frame.n_cam, frame.n_pix, frame.fc);
        let sr = superres.map(|sr| superres_chain::Chain::new(self, sr, frame.chunk)).transpose()?;
        let chunk = sr.as_ref().map_or(frame.chunk, |c| c.images());
        // Features computed only for the network stay on the device.
        let read_fc = if outputs.features || outputs.rgb { fc } else { 0 };
        let readback = |label: &str, size: usize| {
            self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: (size.max(1) * 4) as u64,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        let feat_read = readback("lp3d features readback", chunk * read_fc * n_pix);
        let depth_read = readback("lp3d depth readback", chunk * n_pix);
        let wsum_read = readback("lp3d weights_sum readback", chunk * n_pix);
        let sr_bytes = sr.as_ref().map_or(0, |c| c.device_bytes());
        let frame_bytes = frame.bytes + feat_read.size() + depth_read.size() + wsum_read.size() + sr_bytes;
        self.last_frame_bytes.store(frame_bytes, Ordering::Relaxed);

        let mut features = vec![0f32; n_cam * read_fc * n_pix];
        let mut depth = vec![0f32; n_cam * n_pix];
        let mut weights_sum = vec![0f32; n_cam * n_pix];
        let mut images = sr.as_ref().map(|c| vec![0f32; n_cam * c.floats_per_image()]);
        let mut first = 0usize;
        while first < n_cam {
            let count = chunk.min(n_cam - first);
            let mut encoder = self.encode_chunk(&mut frame, first, count);
            let fbytes = (count * read_fc * n_pix * 4) as u64;
            let pbytes = (count * n_pix * 4) as u64;
            if read_fc > 0 {
                encoder.copy_buffer_to_buffer(&frame.features, 0, &feat_read, 0, fbytes);
            }
            encoder.copy_buffer_to_buffer(&frame.depth, 0, &depth_read, 0, pbytes);
            encoder.copy_buffer_to_buffer(&frame.weights_sum, 0, &wsum_read, 0, pbytes);
            if let Some(c) = &sr {
                c.record(&mut encoder, &frame.features, count);
            }
            self.queue.submit([encoder.finish()]);
            let mut jobs: Vec<(&wgpu::Buffer, u64, &mut [f32])> = vec![
                (&depth_read, pbytes, &mut depth[first * n_pix..(first + count) * n_pix]),
                (&wsum_read, pbytes, &mut weights_sum[first * n_pix..(first + count) * n_pix]),
            ];
            if read_fc > 0 {
                let range = first * read_fc * n_pix..(first + count) * read_fc * n_pix;
                jobs.push((&feat_read, fbytes, &mut features[range]));
            }
            if let (Some(c), Some(images)) = (&sr, images.as_mut()) {
                jobs.push(c.job(first, count, images));
            }
            self.read_back(&mut jobs)?;
            first += count;
        }
        self.check(scope, "render dispatch")?;
        if self.fast_pipeline.get().is_some() {
            self.record_fast_kernel(0);
        }
        // Validated inputs cannot produce NaN/Inf (`check_decoder_range`, `Camera::from_label`);
        // one pass over the results (cheap next to the render) keeps a broken promise from
        // reaching the caller as a silently black image.
        for (name, values, per_cam) in [
            ("features", &features, read_fc * n_pix),
            ("depth", &depth, n_pix),
            ("weights_sum", &weights_sum, n_pix),
        ] {
            if let Some(i) = values.iter().position(|v| !v.is_finite()) {
                return Err(Error::Gpu(format!(
                    "the render produced a non-finite {name} value (camera {}) from validated inputs; \
                     this is a renderer bug, please report it",
                    i / per_cam.max(1)
                )));
            }
        }

        let mut out =
            RenderOutput { n_cameras: n_cam, resolution: settings.resolution as usize, ..Default::default() };
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
        if let (Some(c), Some(images)) = (&sr, &images) {
            c.check_finite(images)?;
        }
        Ok((out, images))
    }

    /// Renders one camera straight into `target` (an `Rgba8Unorm` storage texture of
    /// `resolution`² texels), showing `display`. Nothing is read back: this is the viewer's path.
    pub fn render_to_texture(
        &self,
        tri: &GpuTriplane,
        camera: &Camera,
        settings: &RenderSettings,
        display: Display,
        target: &wgpu::TextureView,
    ) -> Result<()> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let outputs = match display {
            Display::Rgb => Outputs { features: false, rgb: true, depth: false, weights_sum: false },
            Display::Channel(c) if c < 3 => {
                Outputs { features: false, rgb: true, depth: false, weights_sum: false }
            }
            Display::Channel(c) if c < 32 => {
                Outputs { features: true, rgb: false, depth: false, weights_sum: false }
            }
            Display::Channel(c) => {
                return Err(Error::invalid("display", format!("channel {c} is not in 0..32")))
            }
            Display::Depth { .. } | Display::Weights => {
                Outputs { features: false, rgb: false, depth: true, weights_sum: true }
            }
        };
        let mut frame = self.prepare(tri, std::slice::from_ref(camera), settings, outputs)?;
        let uniform = DisplayUniform::new(display);
        let display_buf = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lp3d display"),
            contents: bytemuck::bytes_of(&uniform),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("lp3d present bind group"),
            layout: &self.present_layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: wgpu::BindingResource::TextureView(target) },
                wgpu::BindGroupEntry { binding: 1, resource: display_buf.as_entire_binding() },
            ],
        });
        self.last_frame_bytes.store(frame.bytes + display_buf.size(), Ordering::Relaxed);
        let mut encoder = self.encode_chunk(&mut frame, 0, 1);
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("lp3d present pass"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.present_pipeline);
            pass.set_bind_group(0, &frame.bind_group, &[]);
            pass.set_bind_group(1, &group, &[]);
            let groups = settings.resolution.div_ceil(8);
            pass.dispatch_workgroups(groups, groups, 1);
        }
        self.queue.submit([encoder.finish()]);
        self.check(scope, "render to texture")
    }
}

/// The first error wgpu reports outside an error scope, kept for the next `check` to return
/// (wgpu's default handler would panic).
fn keep_first_uncaptured_error(device: &wgpu::Device) -> Arc<Mutex<Option<String>>> {
    let slot = Arc::new(Mutex::new(None));
    let sink = slot.clone();
    device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
        if let Ok(mut first) = sink.lock() {
            first.get_or_insert_with(|| e.to_string());
        }
    }));
    slot
}
