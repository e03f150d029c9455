//! `lp3d_render`: the Python face of the lp3d renderer. Thin on purpose: conversion and
//! validation live in `convert.rs`, error mapping in `error.rs`, rendering in the
//! `lp3d-renderer` crate. GPU work runs with the GIL released; no panic crosses into Python.

mod convert;
mod error;

use std::hash::BuildHasher;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, OnceLock};

use lp3d_renderer::camera::{FFHQ_FOCAL, FFHQ_PIVOT, FFHQ_RADIUS};
use lp3d_renderer::settings::{MAX_RESOLUTION, MAX_SAMPLES};
use lp3d_renderer::triplane::{HIDDEN, N_CHANNELS, N_OUT};
use lp3d_renderer::{
    occupancy, Camera, Decoder, GpuContext, GpuTriplane, Occupancy, Outputs, PlaneDtype, RenderSettings,
    Renderer, Skips,
};
use numpy::{PyArray1, PyArrayMethods};
use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use convert::{
    bool_arg, camera_array, expect_shape, f32_arg, finite_f32, float_arg, float_array, int_arg, names_arg,
    Arg,
};
use error::{invalid, to_py};

/// EG3D FFHQ's scene bounds (``rendering_kwargs``): the defaults of ``Triplane(...)``. Exposed as
/// module constants; ``lp3d.render.settings.DEFAULT_*`` must agree (tests/test_render_api.py checks, and
/// that the text signatures below spell the same values).
const DEFAULT_BOX_WARP: f64 = 1.0;
const DEFAULT_RAY_START: f64 = 2.25;
const DEFAULT_RAY_END: f64 = 3.3;

struct Gpu {
    info: lp3d_renderer::device::GpuContext,
    renderer: Renderer,
}

/// The process-wide device and pipelines, created on first use and reused.
static GPU: OnceLock<Result<Gpu, String>> = OnceLock::new();

fn gpu(py: Python<'_>) -> PyResult<&'static Gpu> {
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
fn guarded<T>(f: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
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

/// An EG3D-format triplane: planes (3, 32, H, W), the decoder's effective weights and the
/// scene bounds. Immutable; its GPU copy is made on first render and reused.
#[pyclass(module = "lp3d_render", frozen)]
struct Triplane {
    inner: lp3d_renderer::Triplane,
    uploaded: Mutex<Option<Arc<GpuTriplane>>>,
}

impl Triplane {
    fn wrap(inner: lp3d_renderer::Triplane) -> Self {
        Triplane { inner, uploaded: Mutex::new(None) }
    }

    /// The GPU copy, uploaded on first use. With `need_occupancy` and no grid in the triplane,
    /// a grid of the default resolution is baked once and kept with the GPU copy.
    fn on_gpu(&self, gpu: &Gpu, need_occupancy: bool) -> PyResult<Arc<GpuTriplane>> {
        let mut slot = self.uploaded.lock().map_err(|_| PyRuntimeError::new_err("triplane lock poisoned"))?;
        let g = match slot.as_ref() {
            Some(g) => g.clone(),
            None => {
                let g = Arc::new(gpu.renderer.upload(&self.inner).map_err(to_py)?);
                *slot = Some(g.clone());
                g
            }
        };
        if need_occupancy && !g.has_occupancy() {
            let grid = Occupancy::bake(&self.inner, occupancy::DEFAULT_RESOLUTION).map_err(to_py)?;
            gpu.renderer.set_occupancy(&g, grid).map_err(to_py)?;
        }
        Ok(g)
    }
}

fn f32_array<'py>(py: Python<'py>, data: &[f32], shape: &[usize]) -> PyResult<Bound<'py, PyAny>> {
    Ok(PyArray1::from_slice(py, data).reshape(shape)?.into_any())
}

#[pymethods]
impl Triplane {
    #[new]
    #[pyo3(
        signature = (planes, w0, b0, w1, b1, box_warp=Arg::Default(DEFAULT_BOX_WARP),
                     ray_start=Arg::Default(DEFAULT_RAY_START), ray_end=Arg::Default(DEFAULT_RAY_END), *,
                     camera=None, source=None, occupancy=None),
        text_signature = "(planes, w0, b0, w1, b1, box_warp=1.0, ray_start=2.25, ray_end=3.3, *, camera=None, source=None, occupancy=None)"
    )]
    #[allow(clippy::too_many_arguments)]
    fn new<'py>(
        planes: &Bound<'py, PyAny>,
        w0: &Bound<'py, PyAny>,
        b0: &Bound<'py, PyAny>,
        w1: &Bound<'py, PyAny>,
        b1: &Bound<'py, PyAny>,
        box_warp: Arg<'py, f64>,
        ray_start: Arg<'py, f64>,
        ray_end: Arg<'py, f64>,
        camera: Option<&Bound<'py, PyAny>>,
        source: Option<String>,
        occupancy: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Self> {
        guarded(|| {
            let p = float_array(planes, "planes", &["float16", "float32"])?;
            if p.shape.len() != 4 || p.shape[0] != 3 || p.shape[1] != N_CHANNELS {
                return Err(invalid("planes", format!("shape must be (3, 32, H, W), got {:?}", p.shape)));
            }
            let weights = ["float32", "float64"];
            let w0 = float_array(w0, "w0", &weights)?;
            expect_shape(&w0, "w0", &[HIDDEN, N_CHANNELS])?;
            let b0 = float_array(b0, "b0", &weights)?;
            expect_shape(&b0, "b0", &[HIDDEN])?;
            let w1 = float_array(w1, "w1", &weights)?;
            expect_shape(&w1, "w1", &[N_OUT, HIDDEN])?;
            let b1 = float_array(b1, "b1", &weights)?;
            expect_shape(&b1, "b1", &[N_OUT])?;
            let camera = match camera {
                None => None,
                Some(c) => {
                    let (v, batched) = camera_array(c)?;
                    if batched {
                        return Err(invalid("camera", "a triplane's input camera is one (25,) label"));
                    }
                    Some(Camera::from_label(&v, "camera").map_err(to_py)?)
                }
            };
            let occupancy = match occupancy {
                None => None,
                Some(o) => {
                    let a = float_array(o, "occupancy", &["float32"])?;
                    let g = a.shape.first().copied().unwrap_or(0);
                    if a.shape.len() != 3 || a.shape.iter().any(|&d| d != g) {
                        return Err(invalid(
                            "occupancy",
                            format!("shape must be (G, G, G) (Triplane.bake_occupancy), got {:?}", a.shape),
                        ));
                    }
                    Some(Occupancy { resolution: g, bound: a.data })
                }
            };
            let inner = lp3d_renderer::Triplane {
                height: p.shape[2],
                width: p.shape[3],
                plane_dtype: if p.was_f16 { PlaneDtype::F16 } else { PlaneDtype::F32 },
                planes: p.data,
                decoder: Decoder { w0: w0.data, b0: b0.data, w1: w1.data, b1: b1.data },
                box_warp: f32_arg(&box_warp, "box_warp")?,
                ray_start: f32_arg(&ray_start, "ray_start")?,
                ray_end: f32_arg(&ray_end, "ray_end")?,
                camera,
                occupancy,
                source,
            };
            inner.validate().map_err(to_py)?;
            Ok(Triplane::wrap(inner))
        })
    }

    /// Loads a triplane `.npz` file (never with pickle).
    #[staticmethod]
    fn load(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        let inner = py.detach(|| lp3d_renderer::Triplane::load(&path)).map_err(to_py)?;
        Ok(Triplane::wrap(inner))
    }

    /// Writes the triplane `.npz` atomically (temporary file, then rename).
    fn save(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        py.detach(|| self.inner.save(&path)).map_err(to_py)
    }

    /// (3, 32, H, W), float16 or float32 as stored.
    #[getter]
    fn planes<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let t = &self.inner;
        let shape = [3, N_CHANNELS, t.height, t.width];
        match t.plane_dtype {
            PlaneDtype::F32 => f32_array(py, &t.planes, &shape),
            PlaneDtype::F16 => {
                let h: Vec<half::f16> = t.planes.iter().map(|&v| half::f16::from_f32(v)).collect();
                Ok(PyArray1::from_vec(py, h).reshape(shape)?.into_any())
            }
        }
    }
    #[getter]
    fn w0<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        f32_array(py, &self.inner.decoder.w0, &[HIDDEN, N_CHANNELS])
    }
    #[getter]
    fn b0<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        f32_array(py, &self.inner.decoder.b0, &[HIDDEN])
    }
    #[getter]
    fn w1<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        f32_array(py, &self.inner.decoder.w1, &[N_OUT, HIDDEN])
    }
    #[getter]
    fn b1<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        f32_array(py, &self.inner.decoder.b1, &[N_OUT])
    }
    #[getter]
    fn box_warp(&self) -> f32 {
        self.inner.box_warp
    }
    #[getter]
    fn ray_start(&self) -> f32 {
        self.inner.ray_start
    }
    #[getter]
    fn ray_end(&self) -> f32 {
        self.inner.ray_end
    }
    /// The input view's 25-float camera, or None.
    #[getter]
    fn camera<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyAny>>> {
        self.inner.camera.map(|c| f32_array(py, &c.0, &[25])).transpose()
    }
    #[getter]
    fn source(&self) -> Option<String> {
        self.inner.source.clone()
    }
    /// The occupancy grid this triplane carries (G, G, G): per cell, an upper bound on the raw
    /// density (docs/occupancy.md), or None.
    #[getter]
    fn occupancy<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyAny>>> {
        let grid = |o: &Occupancy| f32_array(py, &o.bound, &[o.resolution; 3]);
        self.inner.occupancy.as_ref().map(grid).transpose()
    }

    /// Bakes an occupancy grid (G, G, G) for this triplane on the CPU and returns it (the
    /// triplane is immutable: pass it as ``occupancy=`` to a new Triplane to keep or save it).
    #[pyo3(signature = (resolution=Arg::Default(64)), text_signature = "($self, resolution=64)")]
    fn bake_occupancy<'py>(&self, py: Python<'py>, resolution: Arg<'py, i64>) -> PyResult<Bound<'py, PyAny>> {
        let g = int_arg(&resolution, "resolution", 1, occupancy::MAX_RESOLUTION as i64)? as usize;
        let grid = py.detach(|| guarded(|| Occupancy::bake(&self.inner, g).map_err(to_py)))?;
        f32_array(py, &grid.bound, &[g; 3])
    }

    /// Bytes of device memory the triplane's GPU copy holds (0 before its first render).
    #[getter]
    fn device_bytes(&self) -> PyResult<u64> {
        let slot = self.uploaded.lock().map_err(|_| PyRuntimeError::new_err("triplane lock poisoned"))?;
        Ok(slot.as_ref().map_or(0, |g| g.device_bytes()))
    }

    fn __repr__(&self) -> String {
        let t = &self.inner;
        format!(
            "Triplane(planes=(3, 32, {}, {}) {}, box_warp={}, ray_start={}, ray_end={})",
            t.height,
            t.width,
            if t.plane_dtype == PlaneDtype::F16 { "float16" } else { "float32" },
            t.box_warp,
            t.ray_start,
            t.ray_end
        )
    }
}

/// Renders a triplane from one camera (25,) or a batch (B, 25).
///
/// Returns a dict of float32 arrays: ``features`` (32, R, R), ``rgb`` (3, R, R), ``depth``
/// (R, R), ``weights_sum`` (R, R), each with a leading B axis for a batch of cameras.
/// ``outputs`` restricts what is computed and returned. The defaults are exact EG3D semantics;
/// ``transmittance_threshold`` > 0 stops rays once their transmittance falls below it and
/// ``empty_threshold`` > 0 skips the importance pass of rays whose coarse opacity is below it;
/// their accuracy cost is measured in bench/RESULTS.md. ``occupancy_epsilon`` > 0 skips samples
/// in the empty cells of the triplane's occupancy grid (baked at G = 64 on first use if it has
/// none), at most ``occupancy_epsilon`` opacity per skipped interval (docs/occupancy.md), in the
/// final composite; ``occupancy_coarse`` skips in the coarse pass too (faster; moves the
/// importance samples, so that part of the error is measured, not bounded).
///
/// Every argument is checked here, before any GPU work: a wrong type is a TypeError and a bad
/// value a ValueError, each naming the argument and the value (`resolution=True` and
/// `resolution=32.0` are refused, not read as 1 and 32).
#[pyfunction]
#[pyo3(
    signature = (triplane, camera, resolution=Arg::Default(128), depth_resolution=Arg::Default(48),
                 depth_resolution_importance=Arg::Default(48), deterministic=Arg::Default(true), seed=None,
                 outputs=None, white_back=Arg::Default(false), *,
                 transmittance_threshold=Arg::Default(0.0), empty_threshold=Arg::Default(0.0),
                 occupancy_epsilon=Arg::Default(0.0), occupancy_coarse=Arg::Default(false)),
    text_signature = "(triplane, camera, resolution=128, depth_resolution=48, depth_resolution_importance=48, deterministic=True, seed=None, outputs=None, white_back=False, *, transmittance_threshold=0.0, empty_threshold=0.0, occupancy_epsilon=0.0, occupancy_coarse=False)"
)]
#[allow(clippy::too_many_arguments)]
fn render<'py>(
    py: Python<'py>,
    triplane: &Bound<'py, PyAny>,
    camera: &Bound<'py, PyAny>,
    resolution: Arg<'py, i64>,
    depth_resolution: Arg<'py, i64>,
    depth_resolution_importance: Arg<'py, i64>,
    deterministic: Arg<'py, bool>,
    seed: Option<&Bound<'py, PyAny>>,
    outputs: Option<&Bound<'py, PyAny>>,
    white_back: Arg<'py, bool>,
    transmittance_threshold: Arg<'py, f64>,
    empty_threshold: Arg<'py, f64>,
    occupancy_epsilon: Arg<'py, f64>,
    occupancy_coarse: Arg<'py, bool>,
) -> PyResult<Bound<'py, PyDict>> {
    guarded(|| {
        let tri = triplane.cast::<Triplane>().map_err(|_| {
            invalid(
                "triplane",
                format!("expected lp3d_render.Triplane, got {}", convert::type_name(triplane)),
            )
        })?;
        let (labels, batched) = camera_array(camera)?;
        let cameras = Camera::batch_from_labels(&labels).map_err(to_py)?;
        let deterministic = bool_arg(&deterministic, "deterministic")?;
        let seed = match (deterministic, seed) {
            (true, Some(s)) if !s.is_none() => {
                return Err(invalid("seed", "only applies with deterministic=False"));
            }
            (false, Some(s)) if !s.is_none() => {
                int_arg(&Arg::Given(s.clone()), "seed", 0, u32::MAX as i64)? as u32
            }
            // Jitter without a seed: a fresh one per call, like EG3D's torch.rand.
            (false, _) => std::collections::hash_map::RandomState::new().hash_one(0u8) as u32,
            (true, _) => 0,
        };
        let samples = |arg: &Arg<'py, i64>, field: &str, lo: i64| -> PyResult<u32> {
            Ok(int_arg(arg, field, lo, MAX_SAMPLES as i64)? as u32)
        };
        let settings = RenderSettings {
            resolution: int_arg(&resolution, "resolution", 1, MAX_RESOLUTION as i64)? as u32,
            depth_resolution: samples(&depth_resolution, "depth_resolution", 2)?,
            depth_resolution_importance: samples(
                &depth_resolution_importance,
                "depth_resolution_importance",
                0,
            )?,
            white_back: bool_arg(&white_back, "white_back")?,
            deterministic,
            seed,
            skips: Skips {
                transmittance_threshold: f32_arg(&transmittance_threshold, "transmittance_threshold")?,
                empty_threshold: f32_arg(&empty_threshold, "empty_threshold")?,
                occupancy_epsilon: f32_arg(&occupancy_epsilon, "occupancy_epsilon")?,
                occupancy_coarse: bool_arg(&occupancy_coarse, "occupancy_coarse")?,
            },
        };
        settings.validate().map_err(to_py)?;
        let outputs = match outputs {
            Some(names) if !names.is_none() => {
                Outputs::from_names(&names_arg(names, "outputs")?).map_err(to_py)?
            }
            _ => Outputs::ALL,
        };
        let gpu = gpu(py)?;
        let tri = tri.get();
        let need_grid = settings.skips.occupancy_epsilon > 0.0;
        let uploaded = py.detach(|| guarded(|| tri.on_gpu(gpu, need_grid)))?;
        let out =
            py.detach(|| gpu.renderer.render(&uploaded, &cameras, &settings, outputs)).map_err(to_py)?;

        let r = settings.resolution as usize;
        let b = cameras.len();
        let shape = |c: Option<usize>| -> Vec<usize> {
            let mut s = Vec::new();
            if batched {
                s.push(b);
            }
            if let Some(c) = c {
                s.push(c);
            }
            s.extend([r, r]);
            s
        };
        let dict = PyDict::new(py);
        if let Some(v) = &out.features {
            dict.set_item("features", f32_array(py, v, &shape(Some(N_CHANNELS)))?)?;
        }
        if let Some(v) = &out.rgb {
            dict.set_item("rgb", f32_array(py, v, &shape(Some(3)))?)?;
        }
        if let Some(v) = &out.depth {
            dict.set_item("depth", f32_array(py, v, &shape(None))?)?;
        }
        if let Some(v) = &out.weights_sum {
            dict.set_item("weights_sum", f32_array(py, v, &shape(None))?)?;
        }
        Ok(dict)
    })
}

/// A look-at camera label (25,) from geometric angles in degrees: the renderer crate's
/// `Camera::orbit`, the camera the viewer uses. Matches `lp3d.render.camera.look_at_camera`.
#[pyfunction]
#[pyo3(
    signature = (*, yaw_deg=Arg::Default(0.0), pitch_deg=Arg::Default(0.0), roll_deg=Arg::Default(0.0),
                 radius=Arg::Default(FFHQ_RADIUS), lookat=(FFHQ_PIVOT[0], FFHQ_PIVOT[1], FFHQ_PIVOT[2]),
                 focal=Arg::Default(FFHQ_FOCAL)),
    text_signature = "(*, yaw_deg=0.0, pitch_deg=0.0, roll_deg=0.0, radius=2.7, lookat=(0.0, 0.0, 0.2), focal=4.2647)"
)]
fn look_at_camera<'py>(
    py: Python<'py>,
    yaw_deg: Arg<'py, f64>,
    pitch_deg: Arg<'py, f64>,
    roll_deg: Arg<'py, f64>,
    radius: Arg<'py, f64>,
    lookat: (f64, f64, f64),
    focal: Arg<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    let yaw_deg = float_arg(&yaw_deg, "yaw_deg")?;
    let pitch_deg = float_arg(&pitch_deg, "pitch_deg")?;
    let roll_deg = float_arg(&roll_deg, "roll_deg")?;
    // These two land in the float32 label as they are: they must fit float32.
    let radius = float_arg(&radius, "radius")?;
    finite_f32(radius, "radius")?;
    let focal = float_arg(&focal, "focal")?;
    finite_f32(focal, "focal")?;
    if !(-90.0 < pitch_deg && pitch_deg < 90.0) {
        return Err(invalid("pitch_deg", format!("must be in (-90, 90), got {pitch_deg}")));
    }
    if !(focal.is_finite() && focal > 0.0) {
        return Err(invalid("focal", format!("must be finite and > 0, got {focal}")));
    }
    let c = Camera::orbit(yaw_deg, pitch_deg, roll_deg, radius, [lookat.0, lookat.1, lookat.2], focal);
    f32_array(py, &c.0, &[25])
}

/// Opens the lp3d-view window on a triplane file and blocks until it is closed.
/// With ``screenshot``, renders until the final quality (``resolution``, ``depth_resolution`` +
/// ``depth_resolution_importance``) is on screen, after at least ``frames`` UI frames and, with
/// ``drag_frames``, a scripted drag; saves a PNG of the window, the render as ``*.render.png``
/// and a JSON sidecar (the 3D view's pixel rectangle, every frame's render time and quality) and
/// returns. While the camera moves, frames render at the quality predicted to fit
/// ``frame_budget_ms``. Call from the main thread, once per process (a windowing limitation).
#[cfg(feature = "viewer")]
#[pyfunction]
#[pyo3(
    signature = (path=None, *, screenshot=None, yaw=Arg::Default(0.0), pitch=Arg::Default(0.0),
                 resolution=Arg::Default(128), depth_resolution=Arg::Default(48),
                 depth_resolution_importance=Arg::Default(48), frame_budget_ms=Arg::Default(100.0),
                 frames=Arg::Default(3), drag_frames=Arg::Default(0)),
    text_signature = "(path=None, *, screenshot=None, yaw=0.0, pitch=0.0, resolution=128, depth_resolution=48, depth_resolution_importance=48, frame_budget_ms=100.0, frames=3, drag_frames=0)"
)]
#[allow(clippy::too_many_arguments)]
fn view<'py>(
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
        help: false,
    };
    options.validate().map_err(|e| invalid("view", e))?;
    py.detach(|| guarded(|| lp3d_viewer::run(options).map_err(PyRuntimeError::new_err)))
}

/// Bytes of device memory the last render's own buffers used (outputs, readbacks, uniforms,
/// cameras); the triplane's are ``Triplane.device_bytes``. 0 before the first render.
#[pyfunction]
fn last_frame_device_bytes(py: Python<'_>) -> PyResult<u64> {
    Ok(gpu(py)?.renderer.last_frame_device_bytes())
}

/// The GPU adapter the renderer runs on: backend, name, device type, driver.
/// Raises RuntimeError (with the adapters seen) when none is usable.
#[pyfunction]
fn adapter_info(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let info = &gpu(py)?.info.adapter_info;
    let d = PyDict::new(py);
    d.set_item("backend", format!("{:?}", info.backend).to_lowercase())?;
    d.set_item("name", &info.name)?;
    d.set_item("device_type", format!("{:?}", info.device_type).to_lowercase())?;
    d.set_item("driver", &info.driver)?;
    d.set_item("driver_info", &info.driver_info)?;
    Ok(d)
}

#[pymodule]
fn _lp3d_render(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Triplane>()?;
    m.add_function(wrap_pyfunction!(render, m)?)?;
    m.add_function(wrap_pyfunction!(adapter_info, m)?)?;
    m.add_function(wrap_pyfunction!(last_frame_device_bytes, m)?)?;
    m.add_function(wrap_pyfunction!(look_at_camera, m)?)?;
    #[cfg(feature = "viewer")]
    m.add_function(wrap_pyfunction!(view, m)?)?;
    m.add("MAX_RESOLUTION", MAX_RESOLUTION)?;
    m.add("MAX_SAMPLES", MAX_SAMPLES)?;
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
