//! `shader_sources`: the renderer's WGSL as the renderer compiles it, for a host that compiles it
//! itself (`lp3d share` embeds it in a web page that runs the same stages on WebGPU).

use lp3d_renderer::shaders;
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// The renderer's WGSL stage files (`crates/renderer/shaders/`, compiled into this extension), file
/// name -> source: the render module's in the order the renderer joins them into one module
/// (`shaders::render_module_stages`: the entry points `render_rays`, `depth_bounds_pass`, `present`
/// and `bake_field`), then the super-resolution module's (`sr_conv_up`, `sr_fir_act`, `sr_conv`,
/// `sr_rgb`, bound in group 2). `"\n".join(shader_sources().values())` is one module holding both.
#[pyfunction]
pub fn shader_sources(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let sources = PyDict::new(py);
    for stage in shaders::render_module_stages().into_iter().chain(shaders::superres_module_stages()) {
        sources.set_item(stage.file, stage.source)?;
    }
    Ok(sources)
}
