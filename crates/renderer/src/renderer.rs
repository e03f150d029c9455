//! GPU pipelines and dispatch. The CPU validates and prepares buffers; all rendering work
//! happens in the WGSL kernels of `shaders/` (one ray per invocation).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::thread::JoinHandle;

use wgpu::util::DeviceExt;

use crate::camera::Camera;
use crate::device::GpuContext;
use crate::error::{Error, Result};
use crate::kernel::{build_render_pipeline, fast_kernel_marker, spawn_fast_kernel_compile, write_marker};
// The kernel types' old path (`lp3d_renderer::renderer::KernelChoice`) keeps working.
use crate::gpu_types::{DecoderUniform, DisplayUniform, Params, FLAG_HALF_PLANES};
pub use crate::kernel::{Kernel, KernelChoice};
use crate::occupancy::Occupancy;
use crate::settings::{Outputs, RenderSettings};
use crate::shaders;
use crate::triplane::{PlaneDtype, SceneInfo, Triplane, N_CHANNELS};

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
}

/// The grid (bounds on the CPU) and its bits on the GPU for the last threshold used.
struct GpuOccupancy {
    grid: Arc<Occupancy>,
    bits: Option<(f64, wgpu::Buffer)>,
}

impl GpuTriplane {
    pub fn scene(&self) -> SceneInfo {
        self.scene
    }

    /// Whether the planes are stored as float16 on the device.
    pub fn half_planes(&self) -> bool {
        self.half
    }

    pub fn has_occupancy(&self) -> bool {
        self.occupancy.lock().map(|o| o.is_some()).unwrap_or(false)
    }

    /// Bytes of device memory this triplane holds: planes, decoder and occupancy bits.
    pub fn device_bytes(&self) -> u64 {
        let bits = self
            .occupancy
            .lock()
            .ok()
            .and_then(|o| o.as_ref().and_then(|o| o.bits.as_ref().map(|(_, b)| b.size())))
            .unwrap_or(0);
        self.planes.size() + self.decoder.size() + bits
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

/// Float32's largest value, in float64.
const F32_MAX: f64 = f32::MAX as f64;

/// Refuses a triplane whose finite values could overflow float32 inside the kernel: planes
/// near float32's maximum (3e38) or decoder weights large enough to push the decoder's sums
/// past it would render NaN everywhere — a black image and no error.
///
/// The bound follows `shaders/triplane.wgsl` and `shaders/decoder.wgsl` exactly, in float64:
/// with `P = max |planes|`, every partial sum of the feature accumulation (3 planes x 4
/// bilinear taps, weights summing to 1 per plane) is at most `3P`, and the averaged feature
/// `f` at most `P`; every partial sum of a hidden pre-activation `z_j = w0_j . f + b0_j` is at
/// most `Z_j = sum_k |w0_jk| P + |b0_j|`, so `softplus(z_j) <= Z_j + 1`; every partial sum of
/// an output `o_k = w1_k . h + b1_k` is at most `O_k = sum_j |w1_kj| (Z_j + 1) + |b1_k|`. The
/// ray marcher adds two raw densities before halving them, so it needs `2 O_0`. Colours go
/// through a sigmoid and densities through softplus and `1 - exp(-x)`, which are finite for
/// any finite argument. If all of these stay below float32's maximum (with a margin far above
/// float32's rounding of at most 65-term sums), no intermediate value can be Inf or NaN: a
/// proof for every camera and setting, checked once per upload (one pass over the planes)
/// and covering every path, the viewer's `render_to_texture` included, whose results never
/// come back to the CPU. Real triplanes sit ~30 orders of magnitude below the limit.
pub fn check_decoder_range(tri: &Triplane) -> Result<()> {
    let p = tri.planes.iter().fold(0f64, |m, &v| m.max((v as f64).abs()));
    let d = &tri.decoder;
    let n_in = N_CHANNELS;
    let n_hidden = d.b0.len();
    let hidden: Vec<f64> = (0..n_hidden)
        .map(|j| {
            let row = &d.w0[j * n_in..(j + 1) * n_in];
            row.iter().map(|&w| (w as f64).abs() * p).sum::<f64>() + (d.b0[j] as f64).abs()
        })
        .collect();
    let mut worst = 3.0 * p;
    for (k, b) in d.b1.iter().enumerate() {
        let row = &d.w1[k * n_hidden..(k + 1) * n_hidden];
        let o: f64 = row.iter().zip(&hidden).map(|(&w, &z)| (w as f64).abs() * (z + 1.0)).sum::<f64>()
            + (*b as f64).abs();
        worst = worst.max(if k == 0 { 2.0 * o } else { o });
    }
    worst = hidden.iter().fold(worst, |m, &z| m.max(z));
    // Written so that a NaN bound (impossible for finite inputs) would also be refused.
    if !matches!((worst * 1.001).partial_cmp(&F32_MAX), Some(std::cmp::Ordering::Less)) {
        return Err(Error::invalid(
            "planes",
            format!(
                "the triplane's values overflow float32 in the decoder: planes up to {p:.3e} with \
                 these decoder weights reach {worst:.3e}, beyond float32's maximum {F32_MAX:.3e}"
            ),
        ));
    }
    Ok(())
}

/// What the viewer shows: one render output mapped to colour.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Display {
    Rgb,
    /// Depth as a ramp, near (bright) to far (dark); rays with weights sum < 0.5 are black.
    Depth {
        near: f32,
        far: f32,
    },
    Weights,
    /// One of the 32 feature channels, [-1, 1] mapped to black..white.
    Channel(u32),
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
    /// Where to record that the fast kernel is in Mesa's shader cache (`fast_kernel_marker`),
    /// until a render with the fast kernel has done so.
    pub(crate) marker: Mutex<Option<std::path::PathBuf>>,
    bounds_pipeline: wgpu::ComputePipeline,
    present_layout: wgpu::BindGroupLayout,
    present_pipeline: wgpu::ComputePipeline,
    /// Bound in place of occupancy bits when the skip is off.
    no_occupancy: wgpu::Buffer,
    /// Device bytes of the last frame's own buffers, readbacks included.
    last_frame_bytes: AtomicU64,
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

/// The bind-group and pipeline layouts: the render bindings (shared by every entry point) and
/// the present pass's, which adds the display texture.
struct Layouts {
    render: wgpu::BindGroupLayout,
    render_pipeline_layout: wgpu::PipelineLayout,
    present: wgpu::BindGroupLayout,
    present_pipeline_layout: wgpu::PipelineLayout,
}

impl Layouts {
    fn new(device: &wgpu::Device) -> Layouts {
        let render = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
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
                storage_entry(8, true),
            ],
        });
        let render_pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("lp3d render pipeline layout"),
            bind_group_layouts: &[Some(&render)],
            immediate_size: 0,
        });
        let present = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("lp3d present bindings"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::COMPUTE,
                    ty: wgpu::BindingType::StorageTexture {
                        access: wgpu::StorageTextureAccess::WriteOnly,
                        format: DISPLAY_FORMAT,
                        view_dimension: wgpu::TextureViewDimension::D2,
                    },
                    count: None,
                },
                uniform_entry(1),
            ],
        });
        let present_pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("lp3d present pipeline layout"),
            bind_group_layouts: &[Some(&render), Some(&present)],
            immediate_size: 0,
        });
        Layouts { render, render_pipeline_layout, present, present_pipeline_layout }
    }
}

impl Renderer {
    /// Builds the pipelines on `ctx`'s device (a first dispatch may JIT-compile them), with
    /// the kernels `LP3D_KERNEL` asks for (`KernelChoice::from_env`, default `Auto`).
    pub fn new(ctx: &GpuContext) -> Result<Renderer> {
        Renderer::with_kernel(ctx, KernelChoice::from_env()?)
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
        let no_occupancy = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("lp3d no occupancy"),
            size: 4,
            usage: wgpu::BufferUsages::STORAGE,
            mapped_at_creation: false,
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(Error::Gpu(format!("building the render pipelines failed: {e}")));
        }
        let background = background_compile
            .then(|| spawn_fast_kernel_compile(ctx.adapter_info.name.clone(), marker.clone()))
            .transpose()?;
        Ok(Renderer {
            no_occupancy,
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

    /// Records (once) that the fast kernel has run, so is in Mesa's shader cache. Best effort:
    /// without the marker, the next process only takes the slower `Auto` start.
    fn record_fast_kernel(&self) {
        if let Some(path) = self.marker.lock().ok().and_then(|mut m| m.take()) {
            write_marker(&path);
        }
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

    /// Uploads a validated triplane, with its occupancy grid if it has one. Float16 planes
    /// stay float16 on the device (packed pairs, unpacked to float32 in the kernel).
    pub fn upload(&self, tri: &Triplane) -> Result<GpuTriplane> {
        tri.validate()?;
        check_decoder_range(tri)?;
        let half = tri.plane_dtype == PlaneDtype::F16;
        let planes: Vec<u32> = if half {
            // Channel 2i in the low half, 2i + 1 in the high half (WGSL unpack2x16float).
            tri.planes_channel_last()
                .chunks_exact(2)
                .map(|p| {
                    let lo = half::f16::from_f32(p[0]).to_bits() as u32;
                    let hi = half::f16::from_f32(p[1]).to_bits() as u32;
                    lo | (hi << 16)
                })
                .collect()
        } else {
            tri.planes_channel_last().into_iter().map(f32::to_bits).collect()
        };
        debug_assert_eq!(planes.len() % (N_CHANNELS / 2), 0);
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
        let occupancy = tri.occupancy.clone().map(|grid| GpuOccupancy { grid: Arc::new(grid), bits: None });
        Ok(GpuTriplane { planes, decoder, scene: tri.scene(), half, occupancy: Mutex::new(occupancy) })
    }

    /// Attaches (or replaces) an uploaded triplane's occupancy grid, e.g. one baked after
    /// upload with `Occupancy::bake`. The caller vouches that it was baked for these planes.
    pub fn set_occupancy(&self, tri: &GpuTriplane, grid: Occupancy) -> Result<()> {
        grid.validate()?;
        let mut slot = tri.occupancy.lock().map_err(|_| Error::Gpu("occupancy lock poisoned".into()))?;
        *slot = Some(GpuOccupancy { grid: Arc::new(grid), bits: None });
        Ok(())
    }

    /// Device bytes of the last rendered frame's own buffers (outputs, readbacks, uniforms,
    /// cameras), excluding the triplane's (`GpuTriplane::device_bytes`).
    pub fn last_frame_device_bytes(&self) -> u64 {
        self.last_frame_bytes.load(Ordering::Relaxed)
    }

    /// The occupancy bits for `settings` (grid resolution and buffer), or `None` when the skip
    /// is off. Cached per triplane for the last threshold.
    fn occupancy_bits(
        &self,
        tri: &GpuTriplane,
        settings: &RenderSettings,
    ) -> Result<Option<(u32, wgpu::Buffer)>> {
        let eps = settings.skips.occupancy_epsilon;
        if eps <= 0.0 {
            return Ok(None);
        }
        let mut slot = tri.occupancy.lock().map_err(|_| Error::Gpu("occupancy lock poisoned".into()))?;
        let Some(occ) = slot.as_mut() else {
            return Err(Error::invalid(
                "occupancy_epsilon",
                "this triplane has no occupancy grid: bake one first (Occupancy::bake)",
            ));
        };
        let max_delta = settings.max_interval(tri.scene.bounds.ray_start, tri.scene.bounds.ray_end);
        let threshold = Occupancy::raw_threshold(eps as f64, max_delta);
        if occ.bits.as_ref().map(|(t, _)| *t) != Some(threshold) {
            let buf = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("lp3d occupancy bits"),
                contents: bytemuck::cast_slice(&occ.grid.bits(threshold)),
                usage: wgpu::BufferUsages::STORAGE,
            });
            occ.bits = Some((threshold, buf));
        }
        Ok(occ.bits.as_ref().map(|(_, b)| (occ.grid.resolution as u32, b.clone())))
    }

    /// How many cameras one dispatch renders: the batch is split so each dispatch's outputs
    /// (`fc` feature channels and `n_pix` pixels per camera) fit one storage binding.
    fn cameras_per_dispatch(&self, fc: usize, n_pix: usize, n_cam: usize) -> Result<usize> {
        let max_binding =
            self.limits.max_storage_buffer_binding_size.min(self.limits.max_buffer_size) as usize;
        let per_cam = (fc.max(1) * n_pix * 4).max(1);
        if per_cam > max_binding {
            return Err(Error::invalid(
                "resolution",
                format!("one image's outputs ({} MiB) exceed the device's buffer limit", per_cam >> 20),
            ));
        }
        Ok((max_binding / per_cam).clamp(1, n_cam))
    }

    /// Validates a render request and allocates its buffers and bind group.
    // Long because: every buffer of a frame is made inside one out-of-memory error scope, so
    // that a device that runs out reports it once, as this frame's error.
    fn prepare(
        &self,
        tri: &GpuTriplane,
        cameras: &[Camera],
        settings: &RenderSettings,
        outputs: Outputs,
    ) -> Result<Frame> {
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
        if tri.half {
            params.flags |= FLAG_HALF_PLANES;
        }
        let occupancy = self.occupancy_bits(tri, settings)?;
        if let Some((g, _)) = &occupancy {
            params.occupancy_resolution = *g;
        }

        let chunk = self.cameras_per_dispatch(fc, n_pix, n_cam)?;

        let oom_scope = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let dev = &self.device;
        let storage = |label: &str, size: usize| {
            dev.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: (size.max(1) * 4) as u64,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
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
        let features = storage("lp3d features out", chunk * fc * n_pix);
        let depth = storage("lp3d depth out", chunk * n_pix);
        let weights_sum = storage("lp3d weights_sum out", chunk * n_pix);
        let bind_group = dev.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("lp3d render bind group"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: params_buf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: camera_buf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 2, resource: tri.planes.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 3, resource: tri.decoder.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 4, resource: features.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 5, resource: depth.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 6, resource: weights_sum.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 7, resource: bounds_buf.as_entire_binding() },
                wgpu::BindGroupEntry {
                    binding: 8,
                    resource: occupancy.as_ref().map_or(&self.no_occupancy, |(_, b)| b).as_entire_binding(),
                },
            ],
        });
        let bytes = [&camera_buf, &params_buf, &bounds_buf, &features, &depth, &weights_sum]
            .iter()
            .map(|b| b.size())
            .sum();
        if let Some(e) = pollster::block_on(oom_scope.pop()) {
            return Err(Error::Gpu(format!("out of device memory allocating render buffers: {e}")));
        }
        Ok(Frame {
            params,
            params_buf,
            bind_group,
            features,
            depth,
            weights_sum,
            n_cam,
            n_pix,
            fc,
            chunk,
            bytes,
        })
    }

    /// Records the dispatches for cameras `first..first + count` of a prepared frame (the
    /// batch-global depth bounds pass runs with the first chunk).
    fn encode_chunk(&self, frame: &mut Frame, first: usize, count: usize) -> wgpu::CommandEncoder {
        frame.params.camera_offset = first as u32;
        self.queue.write_buffer(&frame.params_buf, 0, bytemuck::bytes_of(&frame.params));
        let groups_x = (frame.n_pix as u32).div_ceil(WORKGROUP);
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("lp3d render") });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("lp3d render pass"),
                timestamp_writes: None,
            });
            pass.set_bind_group(0, &frame.bind_group, &[]);
            if first == 0 {
                // Batch-global depth range first: render_rays clamps against it.
                pass.set_pipeline(&self.bounds_pipeline);
                pass.dispatch_workgroups(groups_x, frame.n_cam as u32, 1);
            }
            pass.set_pipeline(self.render_pipeline());
            pass.dispatch_workgroups(groups_x, count as u32, 1);
        }
        encoder
    }

    /// Renders `cameras` (one image each) of an uploaded triplane and reads the results back.
    // Long because: the chunk loop dispatches, copies and reads back each chunk before the next
    // reuses the frame's buffers; its steps share those buffers and the running offsets.
    pub fn render(
        &self,
        tri: &GpuTriplane,
        cameras: &[Camera],
        settings: &RenderSettings,
        outputs: Outputs,
    ) -> Result<RenderOutput> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let mut frame = self.prepare(tri, cameras, settings, outputs)?;
        let (n_cam, n_pix, fc, chunk) = (frame.n_cam, frame.n_pix, frame.fc, frame.chunk);
        let readback = |label: &str, size: usize| {
            self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: (size.max(1) * 4) as u64,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        let feat_read = readback("lp3d features readback", chunk * fc * n_pix);
        let depth_read = readback("lp3d depth readback", chunk * n_pix);
        let wsum_read = readback("lp3d weights_sum readback", chunk * n_pix);
        let frame_bytes = frame.bytes + feat_read.size() + depth_read.size() + wsum_read.size();
        self.last_frame_bytes.store(frame_bytes, Ordering::Relaxed);

        let mut features = vec![0f32; n_cam * fc * n_pix];
        let mut depth = vec![0f32; n_cam * n_pix];
        let mut weights_sum = vec![0f32; n_cam * n_pix];
        let mut first = 0usize;
        while first < n_cam {
            let count = chunk.min(n_cam - first);
            let mut encoder = self.encode_chunk(&mut frame, first, count);
            let fbytes = (count * fc * n_pix * 4) as u64;
            let pbytes = (count * n_pix * 4) as u64;
            if fc > 0 {
                encoder.copy_buffer_to_buffer(&frame.features, 0, &feat_read, 0, fbytes);
            }
            encoder.copy_buffer_to_buffer(&frame.depth, 0, &depth_read, 0, pbytes);
            encoder.copy_buffer_to_buffer(&frame.weights_sum, 0, &wsum_read, 0, pbytes);
            self.queue.submit([encoder.finish()]);
            let mut jobs: Vec<(&wgpu::Buffer, u64, &mut [f32])> = vec![
                (&depth_read, pbytes, &mut depth[first * n_pix..(first + count) * n_pix]),
                (&wsum_read, pbytes, &mut weights_sum[first * n_pix..(first + count) * n_pix]),
            ];
            if fc > 0 {
                let range = first * fc * n_pix..(first + count) * fc * n_pix;
                jobs.push((&feat_read, fbytes, &mut features[range]));
            }
            self.read_back(&mut jobs)?;
            first += count;
        }
        self.check(scope, "render dispatch")?;
        if self.fast_pipeline.get().is_some() {
            self.record_fast_kernel();
        }
        // Validated inputs cannot produce NaN/Inf (`check_decoder_range`, `Camera::from_label`);
        // one pass over the results (cheap next to the render) keeps a broken promise from
        // reaching the caller as a silently black image.
        for (name, values, per_cam) in [
            ("features", &features, fc * n_pix),
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
        Ok(out)
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

    /// Pops a validation scope and reports any error wgpu raised meanwhile.
    fn check(&self, scope: wgpu::ErrorScopeGuard, what: &str) -> Result<()> {
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(Error::Gpu(format!("{what} failed: {e}")));
        }
        if let Some(e) = self.uncaptured.lock().ok().and_then(|mut s| s.take()) {
            return Err(Error::Gpu(e));
        }
        Ok(())
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::triplane::SceneBounds;
    use crate::triplane::{Decoder, HIDDEN, N_OUT};

    /// Constant planes and a decoder of constant weights: every bound term is known exactly.
    fn constant(plane: f32, weight: f32) -> Triplane {
        Triplane {
            planes: vec![plane; 3 * N_CHANNELS * 2 * 2],
            height: 2,
            width: 2,
            plane_dtype: PlaneDtype::F32,
            decoder: Decoder {
                w0: vec![weight; HIDDEN * N_CHANNELS],
                b0: vec![0.0; HIDDEN],
                w1: vec![weight; N_OUT * HIDDEN],
                b1: vec![0.0; N_OUT],
            },
            bounds: SceneBounds::default(),
            camera: None,
            occupancy: None,
            source: None,
        }
    }

    #[test]
    fn decoder_range_refuses_planes_that_overflow_float32() {
        // The case: finite planes of 3e38 rendered NaN (the 3-plane sum alone is Inf).
        let e = check_decoder_range(&constant(3e38, 0.1)).unwrap_err().to_string();
        assert!(e.starts_with("planes:") && e.contains("overflow float32"), "{e}");
        // Moderate planes, huge weights: the hidden layer's sums overflow.
        assert!(check_decoder_range(&constant(1.0, 1e37)).is_err());
        // z = 32 * 1e17 * 1e-1 = 3.2e17; o = 64 * 0.1 * (z + 1) = 2.05e17; fine.
        check_decoder_range(&constant(1e17, 0.1)).unwrap();
        // The density's midpoint sum 2 * o_0 is the binding term: o_0 = 64 w (32 w P + 1).
        let w = 1e6f32;
        let p = (f32::MAX as f64 / 2.0 / (64.0 * w as f64 * 32.0 * w as f64)) as f32;
        check_decoder_range(&constant(p * 0.99, w)).unwrap();
        assert!(check_decoder_range(&constant(p * 1.01, w)).is_err());
    }
}
