//! `view`: the lp3d-view window (the `viewer` feature), opened from Python, and
//! `view_options`: its command line, parsed by the viewer's own parser.

use std::path::PathBuf;

use lp3d_renderer::settings::{MAX_RESOLUTION, MAX_SAMPLES};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{bool_arg, float_arg, int_arg, Arg};
use crate::device::guarded;
use crate::error::invalid;

/// Opens the lp3d-view window on a triplane file and blocks until it is closed.
/// With ``screenshot``, renders until the final quality (``resolution``, ``depth_resolution`` +
/// ``depth_resolution_importance``) is on screen, after at least ``frames`` UI frames and, with
/// ``drag_frames``, a scripted drag; saves a PNG of the window, the render as ``*.render.png``
/// and a JSON sidecar (the 3D view's pixel rectangle, every frame's render time and quality) and
/// returns. While the camera moves, frames render at the quality predicted to fit
/// ``frame_budget_ms``; with ``bake`` (the default), once the file's baked field is made (in the
/// background), at the final quality from the field when that fits; with ``fine_field`` (the
/// default) a finer field follows the quick one and replaces it; with ``superres`` (a model
/// package's ``MODEL.superres.npz``) the still image is super-resolved (``lp3d-view --help``). Call from
/// the main thread, once per process (a windowing limitation).
#[pyfunction]
#[pyo3(
    signature = (path=None, *, screenshot=None, yaw=Arg::Default(0.0), pitch=Arg::Default(0.0),
                 resolution=Arg::Default(128), depth_resolution=Arg::Default(48),
                 depth_resolution_importance=Arg::Default(48), frame_budget_ms=Arg::Default(100.0),
                 frames=Arg::Default(3), drag_frames=Arg::Default(0), bake=Arg::Default(true),
                 fine_field=Arg::Default(true), superres=None, no_superres=Arg::Default(false)),
    text_signature = "(path=None, *, screenshot=None, yaw=0.0, pitch=0.0, resolution=128, depth_resolution=48, depth_resolution_importance=48, frame_budget_ms=100.0, frames=3, drag_frames=0, bake=True, fine_field=True, superres=None, no_superres=False)"
)]
#[allow(clippy::too_many_arguments)]
pub fn view<'py>(
    py: Python<'py>,
    path: Option<PathBuf>,
    screenshot: Option<PathBuf>,
    yaw: Arg<'py, f64>,
    pitch: Arg<'py, f64>,
    resolution: Arg<'py, i64>,
    depth_resolution: Arg<'py, i64>,
    depth_resolution_importance: Arg<'py, i64>,
    frame_budget_ms: Arg<'py, f64>,
    frames: Arg<'py, i64>,
    drag_frames: Arg<'py, i64>,
    bake: Arg<'py, bool>,
    fine_field: Arg<'py, bool>,
    superres: Option<PathBuf>,
    no_superres: Arg<'py, bool>,
) -> PyResult<()> {
    let samples = MAX_SAMPLES as i64;
    let options = lp3d_viewer::ViewerOptions {
        path,
        screenshot,
        yaw: float_arg(&yaw, "yaw")?,
        pitch: float_arg(&pitch, "pitch")?,
        resolution: int_arg(&resolution, "resolution", 16, MAX_RESOLUTION as i64)? as u32,
        depth_resolution: int_arg(&depth_resolution, "depth_resolution", 2, samples)? as u32,
        depth_resolution_importance: int_arg(
            &depth_resolution_importance,
            "depth_resolution_importance",
            0,
            samples,
        )? as u32,
        frame_budget_ms: float_arg(&frame_budget_ms, "frame_budget_ms")?,
        frames: int_arg(&frames, "frames", 1, 10_000)? as u32,
        drag_frames: int_arg(&drag_frames, "drag_frames", 0, 10_000)? as u32,
        bake: bool_arg(&bake, "bake")?,
        fine_field: bool_arg(&fine_field, "fine_field")?,
        superres,
        no_superres: bool_arg(&no_superres, "no_superres")?,
        help: false,
    };
    options.validate().map_err(|e| invalid("view", e))?;
    py.detach(|| guarded(|| lp3d_viewer::run(options).map_err(PyRuntimeError::new_err)))
}

/// Parses ``lp3d-view``'s command line (``argv`` without the program name) with the viewer's
/// own parser, the one definition of its flags (``VIEW_USAGE`` lists them), for ``lp3d view``
/// and the ``lp3d-view`` console script. Returns ``help`` (``-h``/``--help`` was given) and
/// ``path`` plus the keyword arguments of :func:`view`; a bad flag or value is a ValueError
/// whose message names it. The files the flags name are checked by :func:`view`.
#[pyfunction]
pub fn view_options<'py>(py: Python<'py>, argv: Vec<String>) -> PyResult<Bound<'py, PyDict>> {
    let o = lp3d_viewer::ViewerOptions::from_args(argv).map_err(PyValueError::new_err)?;
    let dict = PyDict::new(py);
    dict.set_item("help", o.help)?;
    dict.set_item("path", o.path)?;
    dict.set_item("screenshot", o.screenshot)?;
    dict.set_item("yaw", o.yaw)?;
    dict.set_item("pitch", o.pitch)?;
    dict.set_item("resolution", o.resolution)?;
    dict.set_item("depth_resolution", o.depth_resolution)?;
    dict.set_item("depth_resolution_importance", o.depth_resolution_importance)?;
    dict.set_item("frame_budget_ms", o.frame_budget_ms)?;
    dict.set_item("frames", o.frames)?;
    dict.set_item("drag_frames", o.drag_frames)?;
    dict.set_item("bake", o.bake)?;
    dict.set_item("fine_field", o.fine_field)?;
    dict.set_item("superres", o.superres)?;
    dict.set_item("no_superres", o.no_superres)?;
    Ok(dict)
}
