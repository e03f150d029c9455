//! The `Triplane` pyclass: an EG3D-format triplane held in Rust, its argument checks, file
//! I/O and the GPU copy it keeps.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use lp3d_renderer::triplane::{
    DEFAULT_BOX_WARP, DEFAULT_RAY_END, DEFAULT_RAY_START, HIDDEN, N_CHANNELS, N_OUT,
};
use lp3d_renderer::{occupancy, Camera, Decoder, GpuTriplane, Occupancy, PlaneDtype, SceneBounds};
use numpy::{PyArray1, PyArrayMethods};
use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;

use crate::convert::{
    camera_array, expect_shape, f32_array, finite_f32, float_arg, float_array, int_arg, Arg,
};
use crate::device::{guarded, Gpu};
use crate::error::{invalid, to_py};

/// An EG3D-format triplane: planes (3, 32, H, W), the decoder's effective weights and the
/// scene bounds. Immutable; its GPU copy is made on first render and reused.
#[pyclass(module = "lp3d_render", frozen)]
pub struct Triplane {
    inner: lp3d_renderer::Triplane,
    uploaded: Mutex<Option<Arc<GpuTriplane>>>,
}

impl Triplane {
    /// A function's `triplane` argument as a Triplane, or the ValueError naming what it got.
    pub fn arg<'a, 'py>(obj: &'a Bound<'py, PyAny>) -> PyResult<&'a Bound<'py, Triplane>> {
        obj.cast::<Triplane>().map_err(|_| {
            invalid(
                "triplane",
                format!("expected lp3d_render.Triplane, got {}", crate::convert::type_name(obj)),
            )
        })
    }

    fn wrap(inner: lp3d_renderer::Triplane) -> Self {
        Triplane { inner, uploaded: Mutex::new(None) }
    }

    /// The GPU copy, uploaded on first use. With `need_occupancy` and no grid in the triplane,
    /// a grid of the default resolution is baked once and kept with the GPU copy.
    pub fn on_gpu(&self, gpu: &Gpu, need_occupancy: bool) -> PyResult<Arc<GpuTriplane>> {
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

/// A scene bound as given (float64): a number that is finite as float32 (else the same error as
/// `f32_arg`); `SceneBounds::new` checks the rest.
fn bound_arg(arg: &Arg<'_, f64>, field: &str) -> PyResult<f64> {
    let v = float_arg(arg, field)?;
    finite_f32(v, field)?;
    Ok(v)
}

/// Refuses an occupancy grid that does not bound these planes' density: with the checksum it was
/// baked for (a file's `occupancy_checksum`), that checksum must be these planes' and decoder's;
/// without one, the grid must be at least a fresh bake at its resolution in every cell (a looser
/// bound skips less but stays exact; a lower one would skip samples that hold density).
fn check_grid_is_for(tri: &lp3d_renderer::Triplane, checksum: Option<u32>) -> PyResult<()> {
    let Some(grid) = &tri.occupancy else {
        return match checksum {
            Some(_) => Err(invalid("occupancy_checksum", "given without an occupancy grid")),
            None => Ok(()),
        };
    };
    if let Some(stored) = checksum {
        let actual = tri.occupancy_checksum();
        if stored != actual {
            return Err(invalid(
                "occupancy",
                format!(
                    "baked for other planes or another decoder (checksum {stored}, these planes' {actual}): \
                     bake it again with Triplane.bake_occupancy"
                ),
            ));
        }
        return Ok(());
    }
    let fresh = Occupancy::bake(tri, grid.resolution).map_err(to_py)?;
    let g = grid.resolution;
    if let Some(i) = grid.bound.iter().zip(&fresh.bound).position(|(given, need)| given < need) {
        return Err(invalid(
            "occupancy",
            format!(
                "not an upper bound of these planes' density: cell ({}, {}, {}) holds {} where the planes \
                 reach {} (baked for other planes or another decoder?): bake it with Triplane.bake_occupancy",
                i / (g * g),
                (i / g) % g,
                i % g,
                grid.bound[i],
                fresh.bound[i]
            ),
        ));
    }
    Ok(())
}

#[pymethods]
impl Triplane {
    #[new]
    #[pyo3(
        signature = (planes, w0, b0, w1, b1, box_warp=Arg::Default(DEFAULT_BOX_WARP),
                     ray_start=Arg::Default(DEFAULT_RAY_START), ray_end=Arg::Default(DEFAULT_RAY_END), *,
                     camera=None, source=None, occupancy=None, occupancy_checksum=None),
        text_signature = "(planes, w0, b0, w1, b1, box_warp=1.0, ray_start=2.25, ray_end=3.3, *, camera=None, source=None, occupancy=None, occupancy_checksum=None)"
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
        occupancy_checksum: Option<&Bound<'py, PyAny>>,
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
                bounds: SceneBounds::new(
                    bound_arg(&box_warp, "box_warp")?,
                    bound_arg(&ray_start, "ray_start")?,
                    bound_arg(&ray_end, "ray_end")?,
                )
                .map_err(to_py)?,
                camera,
                occupancy,
                source,
            };
            inner.validate().map_err(to_py)?;
            let checksum = match occupancy_checksum {
                Some(c) if !c.is_none() => {
                    Some(int_arg(&Arg::Given(c.clone()), "occupancy_checksum", 0, u32::MAX as i64)? as u32)
                }
                _ => None,
            };
            check_grid_is_for(&inner, checksum)?;
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
        self.inner.bounds.box_warp
    }
    #[getter]
    fn ray_start(&self) -> f32 {
        self.inner.bounds.ray_start
    }
    #[getter]
    fn ray_end(&self) -> f32 {
        self.inner.bounds.ray_end
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
            t.bounds.box_warp,
            t.bounds.ray_start,
            t.bounds.ray_end
        )
    }
}
