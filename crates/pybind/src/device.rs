//! The process-wide GPU (device and pipelines) the bindings share, `guarded` (a Rust panic →
//! RuntimeError), and the device queries `adapter_info` and `last_frame_device_bytes`.

use std::sync::OnceLock;

use lp3d_renderer::{GpuContext, Renderer};
use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

pub struct Gpu {
    pub info: lp3d_renderer::device::GpuContext,
    pub renderer: Renderer,
}

/// The process-wide device and pipelines, created on first use and reused.
static GPU: OnceLock<Result<Gpu, String>> = OnceLock::new();

pub fn gpu(py: Python<'_>) -> PyResult<&'static Gpu> {
    let g = py.detach(|| {
        GPU.get_or_init(|| {
            let ctx = GpuContext::headless().map_err(|e| e.to_string())?;
            let renderer = Renderer::new(&ctx).map_err(|e| e.to_string())?;
            Ok(Gpu { info: ctx, renderer })
        })
    });
    g.as_ref().map_err(|e| PyRuntimeError::new_err(e.clone()))
}

/// Runs `f`, turning a Rust panic into a Python RuntimeError instead of aborting.
pub fn guarded<T>(f: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(p) => {
            let msg = p
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "unknown panic".into());
            Err(PyRuntimeError::new_err(format!("internal renderer error: {msg}")))
        }
    }
}

/// Bytes of device memory the last render's own buffers used (outputs, readbacks, uniforms,
/// cameras); the triplane's are ``Triplane.device_bytes``. 0 before the first render.
#[pyfunction]
pub fn last_frame_device_bytes(py: Python<'_>) -> PyResult<u64> {
    Ok(gpu(py)?.renderer.last_frame_device_bytes())
}

/// The GPU adapter the renderer runs on: backend, name, device type, driver.
/// Raises RuntimeError (with the adapters seen) when none is usable.
#[pyfunction]
pub fn adapter_info(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let info = &gpu(py)?.info.adapter_info;
    let d = PyDict::new(py);
    d.set_item("backend", format!("{:?}", info.backend).to_lowercase())?;
    d.set_item("name", &info.name)?;
    d.set_item("device_type", format!("{:?}", info.device_type).to_lowercase())?;
    d.set_item("driver", &info.driver)?;
    d.set_item("driver_info", &info.driver_info)?;
    Ok(d)
}
