//! `lp3d_render`: the Python face of the lp3d renderer. Thin on purpose: conversion and
//! validation live in `convert.rs`, error mapping in `error.rs`, rendering in the
//! `lp3d-renderer` crate. GPU work runs with the GIL released; no panic crosses into Python.
//!
//! One module per Python type or function: `triplane.rs` (`Triplane`), `render.rs` (`render`),
//! `baked.rs` (`bake`, `BakedField`),
//! `camera.rs` (`look_at_camera`), `shaders.rs` (`shader_sources`), `view.rs` (`view`),
//! `superres.rs` (`SuperRes`, the super-resolution network on the GPU),
//! `device.rs` (the shared GPU, `adapter_info`, `last_frame_device_bytes`); this file registers
//! them and the constants.

mod baked;
mod camera;
mod convert;
mod device;
mod error;
mod render;
mod shaders;
mod superres;
mod triplane;
#[cfg(feature = "viewer")]
mod view;

use lp3d_renderer::camera::{FFHQ_FOCAL, FFHQ_PIVOT, FFHQ_RADIUS};
use lp3d_renderer::settings::{MAX_RESOLUTION, MAX_SAMPLES};
use lp3d_renderer::Skips;
// EG3D FFHQ's scene bounds: the defaults of ``Triplane(...)``, exposed as module constants;
// ``lp3d.render.settings.DEFAULT_*`` must agree (tests/render/test_render_api.py checks, and that the
// text signatures in triplane.rs spell the same values).
use lp3d_renderer::triplane::{DEFAULT_BOX_WARP, DEFAULT_RAY_END, DEFAULT_RAY_START};
use pyo3::prelude::*;
use pyo3::types::PyDict;

#[pymodule]
fn _lp3d_render(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<triplane::Triplane>()?;
    m.add_class::<baked::BakedField>()?;
    m.add_class::<superres::SuperRes>()?;
    m.add_function(wrap_pyfunction!(baked::bake, m)?)?;
    m.add_function(wrap_pyfunction!(baked::attach_baked, m)?)?;
    m.add_function(wrap_pyfunction!(render::render, m)?)?;
    m.add_function(wrap_pyfunction!(device::adapter_info, m)?)?;
    m.add_function(wrap_pyfunction!(device::last_frame_device_bytes, m)?)?;
    m.add_function(wrap_pyfunction!(camera::look_at_camera, m)?)?;
    m.add_function(wrap_pyfunction!(shaders::shader_sources, m)?)?;
    #[cfg(feature = "viewer")]
    {
        m.add_function(wrap_pyfunction!(view::view, m)?)?;
        m.add_function(wrap_pyfunction!(view::view_options, m)?)?;
        m.add("VIEW_USAGE", lp3d_viewer::USAGE)?;
    }
    m.add("MAX_RESOLUTION", MAX_RESOLUTION)?;
    m.add("MAX_SAMPLES", MAX_SAMPLES)?;
    // Skips::BAKED, for the test that ties it to lp3d.render.settings.BAKED.
    m.add("BAKED_SUBDIVISIONS", Skips::BAKED.baked_subdivisions)?;
    m.add("BAKED_FINE_SUBDIVISIONS", Skips::BAKED.baked_fine_subdivisions)?;
    m.add("BAKED_OCCUPANCY_EPSILON", Skips::BAKED.occupancy_epsilon)?;
    m.add("FFHQ_FOCAL", FFHQ_FOCAL)?;
    m.add("FFHQ_RADIUS", FFHQ_RADIUS)?;
    m.add("FFHQ_PIVOT", (FFHQ_PIVOT[0], FFHQ_PIVOT[1], FFHQ_PIVOT[2]))?;
    m.add("DEFAULT_BOX_WARP", DEFAULT_BOX_WARP)?;
    m.add("DEFAULT_RAY_START", DEFAULT_RAY_START)?;
    m.add("DEFAULT_RAY_END", DEFAULT_RAY_END)?;
    m.add("PLANE_AXES", lp3d_renderer::triplane::PLANE_AXES.map(|a| (a[0], a[1])).to_vec())?;
    m.add("FORMAT_VERSION", lp3d_renderer::triplane::FORMAT_VERSION)?;
    // The triplane file's caps by name; lp3d.render.triplane_io.FILE_LIMITS must agree (a test checks).
    let limits = PyDict::new(m.py());
    for (name, value) in lp3d_renderer::triplane::FILE_LIMITS {
        limits.set_item(name, value)?;
    }
    m.add("FILE_LIMITS", limits)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
