//! `shader_sources`: the renderer's WGSL as the renderer compiles it, for a host that compiles it
//! itself (`lp3d share` embeds it in a web page that runs the same stages on WebGPU).

use lp3d_renderer::shaders;
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// The stage files of the renderer's WGSL module (`crates/renderer/shaders/`, compiled into this
/// extension), file name -> source, in the order the renderer joins them into one module
/// (`shaders::render_module_stages`): `"\n".join(shader_sources().values())` is the module source
/// the renderer compiles, with the entry points `render_rays`, `depth_bounds_pass` and `present`.
#[pyfunction]
pub fn shader_sources(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let sources = PyDict::new(py);
    for stage in shaders::render_module_stages() {
        sources.set_item(stage.file, stage.source)?;
    }
    Ok(sources)
}
