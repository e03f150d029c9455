//! The four pipelines of `shaders/superres.wgsl`, built once per device and shared by every
//! network on it.

use crate::error::{Error, Result};
use crate::shaders;

/// The four pipelines of `shaders/superres.wgsl` and their one bind-group layout, for a device.
pub struct SuperresKernels {
    pub(super) device: wgpu::Device,
    pub(super) layout: wgpu::BindGroupLayout,
    pub(super) conv_up: wgpu::ComputePipeline,
    pub(super) fir_act: wgpu::ComputePipeline,
    pub(super) conv: wgpu::ComputePipeline,
    pub(super) rgb: wgpu::ComputePipeline,
    /// Bound where a kernel reads no skip image.
    pub(super) placeholder: wgpu::Buffer,
}

impl SuperresKernels {
    /// Builds the pipelines (on lavapipe each compiles at its first dispatch).
    pub fn new(device: &wgpu::Device) -> Result<SuperresKernels> {
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("lp3d superres module"),
            source: wgpu::ShaderSource::Wgsl(shaders::superres_module_source().into()),
        });
        let entry = |binding: u32, ty: wgpu::BufferBindingType| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer { ty, has_dynamic_offset: false, min_binding_size: None },
            count: None,
        };
        let read = wgpu::BufferBindingType::Storage { read_only: true };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("lp3d superres bindings"),
            entries: &[
                entry(0, wgpu::BufferBindingType::Uniform),
                entry(1, read),
                entry(2, read),
                entry(3, wgpu::BufferBindingType::Storage { read_only: false }),
                entry(4, read),
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("lp3d superres pipeline layout"),
            // `shaders/superres.wgsl` binds group 2 (groups 0 and 1 are the render module's).
            bind_group_layouts: &[None, None, Some(&layout)],
            immediate_size: 0,
        });
        let make = |name: &str| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(name),
                layout: Some(&pipeline_layout),
                module: &module,
                entry_point: Some(name),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let kernels = SuperresKernels {
            device: device.clone(),
            conv_up: make(shaders::SR_CONV_UP.name),
            fir_act: make(shaders::SR_FIR_ACT.name),
            conv: make(shaders::SR_CONV.name),
            rgb: make(shaders::SR_RGB.name),
            placeholder: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("lp3d superres no skip"),
                size: 16,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            }),
            layout,
        };
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(Error::Gpu(format!("building the super-resolution pipelines failed: {e}")));
        }
        Ok(kernels)
    }
}
