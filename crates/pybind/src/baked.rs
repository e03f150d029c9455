//! `bake` and the `BakedField` it returns: a triplane's field decoded once into a grid
//! (`docs/baked.md`), kept with the triplane's GPU copy so that `render(...,
//! baked_subdivisions=k)` looks samples up instead of decoding them.

use std::sync::Arc;

use lp3d_renderer::baked::{BrickLayout, EMPTY, MAX_FINE_SUBDIVISIONS, MAX_SUBDIVISIONS};
use lp3d_renderer::settings::MAX_SAMPLES;
use lp3d_renderer::{BakeSpec, GpuBaked, RenderSettings, Skips};
use numpy::{PyArray1, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::convert::{self, bool_arg, f32_arg, float_arg, int_arg, Arg};
use crate::device::{gpu, guarded};
use crate::error::{invalid, to_py};
use crate::triplane::Triplane;

/// A baked field on the GPU: per baked cell a brick of (k + 1)³ points of (sigma_raw, r, g,
/// b) float16, in the cells the occupancy skip keeps (docs/baked.md).
#[pyclass(module = "lp3d_render", frozen)]
pub struct BakedField {
    inner: Arc<GpuBaked>,
}

impl BakedField {
    /// The points of one level, read back: (bricks, k + 1, k + 1, k + 1, 4) float16.
    fn level<'py>(&self, py: Python<'py>, fine: bool) -> PyResult<Bound<'py, PyAny>> {
        let g = gpu(py)?;
        let halves = py.detach(|| g.renderer.read_baked_values(&self.inner, fine)).map_err(to_py)?;
        let (k, n) = match fine {
            false => (self.inner.spec.subdivisions, self.inner.n_coarse()),
            true => (self.inner.spec.fine_subdivisions, self.inner.n_bricks - self.inner.n_coarse()),
        };
        let k1 = k as usize + 1;
        let arr = PyArray1::from_vec(py, halves).reshape([n, k1, k1, k1, 4])?;
        arr.call_method1("view", ("float16",))
    }
}

#[pymethods]
impl BakedField {
    /// Points per baked cell edge, k.
    #[getter]
    fn subdivisions(&self) -> u32 {
        self.inner.spec.subdivisions
    }
    /// A two-level field's points per cell edge in the bricks a surface crosses; 0 for one level.
    #[getter]
    fn fine_subdivisions(&self) -> u32 {
        self.inner.spec.fine_subdivisions
    }
    /// The occupancy skip's per-interval opacity bound the bake kept cells for.
    #[getter]
    fn occupancy_epsilon(&self) -> f32 {
        self.inner.spec.epsilon
    }
    /// The longest sample interval (scene units) the bake covers.
    #[getter]
    fn max_delta(&self) -> f64 {
        self.inner.spec.max_delta
    }
    /// Baked cells per axis, G: the occupancy grid's, or blocks of its cells (docs/baked.md).
    #[getter]
    fn cells(&self) -> usize {
        self.inner.cells
    }
    /// Cells that hold a brick.
    #[getter]
    fn bricks(&self) -> usize {
        self.inner.n_bricks
    }
    /// Of those, the fine bricks of a two-level field (numbered after the coarse ones).
    #[getter]
    fn fine_bricks(&self) -> usize {
        self.inner.n_bricks - self.inner.n_coarse()
    }
    #[getter]
    fn bake_seconds(&self) -> f64 {
        self.inner.bake_seconds
    }
    #[getter]
    fn device_bytes(&self) -> u64 {
        self.inner.device_bytes()
    }
    /// (G, G, G) int64: each cell's brick number, -1 for a cell without one.
    #[getter]
    fn index<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let idx: Vec<i64> =
            self.inner.index.iter().map(|&b| if b == EMPTY { -1 } else { b as i64 }).collect();
        Ok(PyArray1::from_vec(py, idx).reshape([self.inner.cells; 3])?.into_any())
    }
    /// (coarse bricks, k + 1, k + 1, k + 1, 4) float16: (sigma_raw, w r, w g, w b) at each point of
    /// the bricks numbered below ``bricks - fine_bricks``, read back from the GPU; point (a, b, c)
    /// of the brick of cell (ix, iy, iz) sits at plane coordinates -1 + 2 ((ix, iy, iz) k + (a, b,
    /// c)) / (G k).
    #[getter]
    fn values<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        self.level(py, false)
    }
    /// (fine bricks, k_f + 1, k_f + 1, k_f + 1, 4) float16: a two-level field's fine bricks, as
    /// ``values`` with k_f = ``fine_subdivisions`` (empty for one level).
    #[getter]
    fn fine_values<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        self.level(py, true)
    }
    fn __repr__(&self) -> String {
        format!(
            "BakedField(subdivisions={}, fine_subdivisions={}, cells={}, bricks={}, fine_bricks={}, \
             occupancy_epsilon={}, {:.1} MiB)",
            self.inner.spec.subdivisions,
            self.inner.spec.fine_subdivisions,
            self.inner.cells,
            self.inner.n_bricks,
            self.inner.n_bricks - self.inner.n_coarse(),
            self.inner.spec.epsilon,
            self.inner.device_bytes() as f64 / (1 << 20) as f64
        )
    }
}

/// Bakes ``triplane``'s field on the GPU for renders with ``baked_subdivisions=subdivisions``,
/// ``occupancy_epsilon`` and sample intervals up to those of ``depth_resolution`` coarse samples
/// (jittered or not), keeps it with the triplane and returns it. ``render`` bakes on first use
/// too; call this to time the bake, to bake before the first frame, or to read the field.
/// ``progress(done, total)``, if given, is called after each GPU dispatch of the bake (points
/// done, points in all); an exception it raises stops the bake and is raised here.
#[pyfunction]
#[pyo3(
    signature = (triplane, subdivisions=Arg::Default(4), occupancy_epsilon=Arg::Default(1e-4),
                 depth_resolution=Arg::Default(48), deterministic=Arg::Default(true), progress=None,
                 fine_subdivisions=Arg::Default(0)),
    text_signature = "(triplane, subdivisions=4, occupancy_epsilon=0.0001, depth_resolution=48, deterministic=True, progress=None, fine_subdivisions=0)"
)]
#[allow(clippy::too_many_arguments)]
pub fn bake<'py>(
    py: Python<'py>,
    triplane: &Bound<'py, PyAny>,
    subdivisions: Arg<'py, i64>,
    occupancy_epsilon: Arg<'py, f64>,
    depth_resolution: Arg<'py, i64>,
    deterministic: Arg<'py, bool>,
    progress: Option<Bound<'py, PyAny>>,
    fine_subdivisions: Arg<'py, i64>,
) -> PyResult<BakedField> {
    guarded(|| {
        let tri = Triplane::arg(triplane)?;
        let k = int_arg(&subdivisions, "subdivisions", 1, MAX_SUBDIVISIONS as i64)? as u32;
        let fine = int_arg(&fine_subdivisions, "fine_subdivisions", 0, MAX_FINE_SUBDIVISIONS as i64)? as u32;
        if fine != 0 && fine <= k {
            return Err(invalid(
                "fine_subdivisions",
                format!("must be 0 or above subdivisions ({k}), got {fine}"),
            ));
        }
        let settings = RenderSettings {
            depth_resolution: int_arg(&depth_resolution, "depth_resolution", 4, MAX_SAMPLES as i64)? as u32,
            deterministic: bool_arg(&deterministic, "deterministic")?,
            skips: Skips {
                occupancy_epsilon: f32_arg(&occupancy_epsilon, "occupancy_epsilon")?,
                baked_subdivisions: k,
                baked_fine_subdivisions: fine,
                ..Skips::EXACT
            },
            ..RenderSettings::default()
        };
        settings.validate().map_err(to_py)?;
        let g = gpu(py)?;
        let tri = tri.get();
        let uploaded = py.detach(|| guarded(|| tri.on_gpu(g, true)))?;
        let bounds = uploaded.scene().bounds;
        let spec = BakeSpec {
            subdivisions: k,
            fine_subdivisions: fine,
            epsilon: settings.skips.occupancy_epsilon,
            max_delta: settings.max_interval(bounds.ray_start, bounds.ray_end),
        };
        let callback = match progress {
            Some(p) if !p.is_none() => {
                if !p.is_callable() {
                    return Err(invalid(
                        "progress",
                        format!("must be callable, got {}", convert::type_name(&p)),
                    ));
                }
                Some(p.unbind())
            }
            _ => None,
        };
        let mut raised: Option<PyErr> = None;
        let baked = py.detach(|| {
            g.renderer.bake_with_progress(&uploaded, spec, &mut |done, total| match &callback {
                None => true,
                Some(f) => {
                    Python::attach(|py| f.call1(py, (done, total)).map_err(|e| raised = Some(e)).is_ok())
                }
            })
        });
        if let Some(e) = raised {
            return Err(e);
        }
        let inner = baked.map_err(to_py)?;
        debug_assert_eq!(BrickLayout::points_per_brick(k), (k as usize + 1).pow(3));
        Ok(BakedField { inner })
    })
}

/// Attaches a field saved earlier (``lp3d.render.baked.load_baked`` reads the file and checks it
/// belongs to ``triplane``) to the triplane's GPU copy: ``index`` (G, G, G) int64 (-1 empty),
/// ``values`` (bricks, k+1, k+1, k+1, 4) float16 bits as uint16, and for a two-level field
/// (``fine_subdivisions`` > 0) ``fine_values`` (fine bricks, k_f+1, k_f+1, k_f+1, 4) the same way.
/// Every array is checked here.
#[pyfunction]
#[pyo3(
    signature = (triplane, index, values, *, subdivisions, occupancy_epsilon, max_delta,
                 fine_subdivisions=Arg::Default(0), fine_values=None),
    text_signature = "(triplane, index, values, *, subdivisions, occupancy_epsilon, max_delta, fine_subdivisions=0, fine_values=None)"
)]
#[allow(clippy::too_many_arguments)]
pub fn attach_baked<'py>(
    py: Python<'py>,
    triplane: &Bound<'py, PyAny>,
    index: &Bound<'py, PyAny>,
    values: &Bound<'py, PyAny>,
    subdivisions: Arg<'py, i64>,
    occupancy_epsilon: Arg<'py, f64>,
    max_delta: Arg<'py, f64>,
    fine_subdivisions: Arg<'py, i64>,
    fine_values: Option<&Bound<'py, PyAny>>,
) -> PyResult<BakedField> {
    guarded(|| {
        let tri = Triplane::arg(triplane)?;
        let index = index
            .cast::<numpy::PyArrayDyn<i64>>()
            .map_err(|_| invalid("index", "expected an int64 array (G, G, G)"))?;
        let values = values
            .cast::<numpy::PyArrayDyn<u16>>()
            .map_err(|_| invalid("values", "expected a uint16 array of float16 bits"))?;
        let shape = index.shape().to_vec();
        if shape.len() != 3 || shape[0] != shape[1] || shape[1] != shape[2] {
            return Err(invalid("index", format!("must be (G, G, G), got {shape:?}")));
        }
        let index: Vec<u32> = index
            .to_vec()
            .map_err(|_| invalid("index", "must be contiguous"))?
            .into_iter()
            .map(|b| if b < 0 { EMPTY } else { u32::try_from(b).unwrap_or(EMPTY - 1) })
            .collect();
        let values = values.to_vec().map_err(|_| invalid("values", "must be contiguous"))?;
        let fine_values = match fine_values {
            Some(f) if !f.is_none() => f
                .cast::<numpy::PyArrayDyn<u16>>()
                .map_err(|_| invalid("fine_values", "expected a uint16 array of float16 bits"))?
                .to_vec()
                .map_err(|_| invalid("fine_values", "must be contiguous"))?,
            _ => Vec::new(),
        };
        // Every scalar through the one validating conversion: a huge int or float is a ValueError
        // naming the argument, never PyO3's OverflowError.
        let fine = int_arg(&fine_subdivisions, "fine_subdivisions", 0, MAX_FINE_SUBDIVISIONS as i64)? as u32;
        let k = int_arg(&subdivisions, "subdivisions", 1, MAX_SUBDIVISIONS as i64)? as u32;
        let spec = BakeSpec {
            subdivisions: k,
            fine_subdivisions: fine,
            epsilon: f32_arg(&occupancy_epsilon, "occupancy_epsilon")?,
            max_delta: float_arg(&max_delta, "max_delta")?,
        };
        let g = gpu(py)?;
        let tri = tri.get();
        let uploaded = py.detach(|| guarded(|| tri.on_gpu(g, true)))?;
        let inner = py
            .detach(|| g.renderer.attach_baked(&uploaded, spec, shape[0], index, &values, &fine_values))
            .map_err(to_py)?;
        Ok(BakedField { inner })
    })
}
