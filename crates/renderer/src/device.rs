//! The wgpu device the renderer runs on: created headless once (Python, tests, benchmarks)
//! or borrowed from the viewer's eframe context.

use crate::error::{Error, Result};

pub struct GpuContext {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub adapter_info: wgpu::AdapterInfo,
    pub limits: wgpu::Limits,
}

impl GpuContext {
    /// Creates a device without a window. Honours `WGPU_BACKEND`, `WGPU_ADAPTER_NAME` and
    /// `WGPU_POWER_PREF`; fails with the list of adapters seen when none is usable.
    pub fn headless() -> Result<GpuContext> {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(wgpu::util::initialize_adapter_from_env_or_default(&instance, None))
            .map_err(|e| {
                let seen: Vec<String> = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()))
                    .iter()
                    .map(|a| {
                        let i = a.get_info();
                        format!("{} ({:?}, {:?})", i.name, i.backend, i.device_type)
                    })
                    .collect();
                Error::Gpu(format!(
                    "no usable GPU adapter ({e}); adapters seen: {seen:?}. On a machine without a GPU install \
                     Mesa's lavapipe (apt-get install mesa-vulkan-drivers libvulkan1) and set WGPU_BACKEND=vulkan"
                ))
            })?;
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("lp3d renderer device"),
            required_features: wgpu::Features::empty(),
            // Ask for what the adapter offers: large triplanes and batches need big storage buffers.
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| Error::Gpu(format!("request_device failed: {e}")))?;
        Ok(GpuContext { device, queue, adapter_info: adapter.get_info(), limits })
    }

    /// Wraps a device someone else created (the viewer passes eframe's).
    pub fn from_device(
        device: wgpu::Device,
        queue: wgpu::Queue,
        adapter_info: wgpu::AdapterInfo,
    ) -> GpuContext {
        let limits = device.limits();
        GpuContext { device, queue, adapter_info, limits }
    }
}
