//! The `SuperRes` pyclass: a folded super-resolution network (`lp3d.nets.superres`'s
//! `FoldedSuperResolution`) resident on the shared GPU, built from its weight arrays and applied
//! to feature images (`lp3d_renderer::superres`).

use std::sync::{Arc, OnceLock};

use lp3d_renderer::superres::{SuperresBlock, SuperresKernels, SuperresWeights, MAX_OUTPUT_RESOLUTION};
use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use crate::convert::{expect_shape, f32_array, float_array, int_arg, type_name, Arg, FloatArray};
use crate::device::{gpu, guarded};
use crate::error::{invalid, to_py};

/// The super-resolution pipelines on the shared device, built on first use.
static KERNELS: OnceLock<Result<Arc<SuperresKernels>, String>> = OnceLock::new();

const WEIGHT_DTYPES: [&str; 2] = ["float32", "float64"];

/// A list argument of one array per block; `field[i]` names each.
fn arrays(obj: &Bound<'_, PyAny>, field: &str, blocks: Option<usize>) -> PyResult<Vec<FloatArray>> {
    let items: Vec<Bound<'_, PyAny>> = match obj.cast::<pyo3::types::PyList>() {
        Ok(list) => list.iter().collect(),
        Err(_) => match obj.cast::<pyo3::types::PyTuple>() {
            Ok(t) => t.iter().collect(),
            Err(_) => {
                return Err(invalid(
                    field,
                    format!("expected a list of numpy arrays (one per block), got {}", type_name(obj)),
                ))
            }
        },
    };
    if let Some(n) = blocks {
        if items.len() != n {
            return Err(invalid(
                field,
                format!("expected {n} arrays (one per block, as convs_up has), got {}", items.len()),
            ));
        }
    }
    items.iter().enumerate().map(|(i, a)| float_array(a, &format!("{field}[{i}]"), &WEIGHT_DTYPES)).collect()
}

/// A folded super-resolution network on the GPU: feature images (B, C, R, R) in, images
/// (B, 3, R·2^blocks, R·2^blocks) out. The weights are `FoldedSuperResolution`'s, one array per
/// block each.
#[pyclass(module = "lp3d_render", frozen)]
pub struct SuperRes {
    inner: lp3d_renderer::SuperRes,
}

impl SuperRes {
    /// Checked `weights` resident on the shared GPU.
    fn on_gpu(py: Python<'_>, weights: &SuperresWeights) -> PyResult<SuperRes> {
        let g = gpu(py)?;
        let kernels = py
            .detach(|| {
                KERNELS.get_or_init(|| {
                    SuperresKernels::new(&g.info.device).map(Arc::new).map_err(|e| e.to_string())
                })
            })
            .as_ref()
            .map_err(|e| PyRuntimeError::new_err(e.clone()))?
            .clone();
        let inner = py.detach(|| lp3d_renderer::SuperRes::new(&g.info, kernels, weights)).map_err(to_py)?;
        Ok(SuperRes { inner })
    }

    /// The network on the GPU, for `render(..., superres=)`.
    pub fn network(&self) -> &lp3d_renderer::SuperRes {
        &self.inner
    }
}

#[pymethods]
impl SuperRes {
    #[new]
    #[pyo3(
        signature = (convs_up, biases_up, convs, biases, rgb_weights, rgb_biases, *, input_resolution),
        text_signature = "(convs_up, biases_up, convs, biases, rgb_weights, rgb_biases, *, input_resolution)"
    )]
    #[allow(clippy::too_many_arguments)]
    fn new<'py>(
        py: Python<'py>,
        convs_up: &Bound<'py, PyAny>,
        biases_up: &Bound<'py, PyAny>,
        convs: &Bound<'py, PyAny>,
        biases: &Bound<'py, PyAny>,
        rgb_weights: &Bound<'py, PyAny>,
        rgb_biases: &Bound<'py, PyAny>,
        input_resolution: Arg<'py, i64>,
    ) -> PyResult<Self> {
        guarded(|| {
            let r =
                int_arg(&input_resolution, "input_resolution", 1, MAX_OUTPUT_RESOLUTION as i64 / 2)? as usize;
            let up = arrays(convs_up, "convs_up", None)?;
            if up.is_empty() {
                return Err(invalid("convs_up", "expected one array per ×2 block, got none"));
            }
            let n = Some(up.len());
            let (bu, cv, bs, rw, rb) = (
                arrays(biases_up, "biases_up", n)?,
                arrays(convs, "convs", n)?,
                arrays(biases, "biases", n)?,
                arrays(rgb_weights, "rgb_weights", n)?,
                arrays(rgb_biases, "rgb_biases", n)?,
            );
            let in_channels = match up[0].shape.as_slice() {
                [_, cin, 3, 3] => *cin,
                s => {
                    return Err(invalid(
                        "convs_up[0]",
                        format!("shape must be (C_out, C_in, 3, 3), got {s:?}"),
                    ))
                }
            };
            let mut cin = in_channels;
            let mut blocks = Vec::new();
            for (i, (((((u, bu), cv), bs), rw), rb)) in
                up.into_iter().zip(bu).zip(cv).zip(bs).zip(rw).zip(rb).enumerate()
            {
                let c = u.shape.first().copied().unwrap_or(0);
                expect_shape(&u, &format!("convs_up[{i}]"), &[c, cin, 3, 3])?;
                expect_shape(&bu, &format!("biases_up[{i}]"), &[c])?;
                expect_shape(&cv, &format!("convs[{i}]"), &[c, c, 3, 3])?;
                expect_shape(&bs, &format!("biases[{i}]"), &[c])?;
                expect_shape(&rw, &format!("rgb_weights[{i}]"), &[3, c, 1, 1])?;
                expect_shape(&rb, &format!("rgb_biases[{i}]"), &[3])?;
                blocks.push(SuperresBlock {
                    channels: c,
                    conv_up: u.data,
                    bias_up: bu.data,
                    conv: cv.data,
                    bias: bs.data,
                    rgb_weight: rw.data,
                    rgb_bias: rb.data,
                });
                cin = c;
            }
            let weights = SuperresWeights { in_channels, input_resolution: r, blocks };
            weights.validate().map_err(to_py)?;
            SuperRes::on_gpu(py, &weights)
        })
    }

    /// The network of a model package's weights file (`MODEL.superres.npz`), read and checked by
    /// the renderer's reader (`lp3d_renderer::SuperresWeights::load`; errors name the file and key).
    #[staticmethod]
    fn load(py: Python<'_>, path: std::path::PathBuf) -> PyResult<SuperRes> {
        guarded(|| {
            let weights = py.detach(|| SuperresWeights::load(&path)).map_err(to_py)?;
            SuperRes::on_gpu(py, &weights)
        })
    }

    /// Channels of the feature image the network takes (rgb = the first 3).
    #[getter]
    fn in_channels(&self) -> usize {
        self.inner.in_channels()
    }

    /// Side of the feature image it takes.
    #[getter]
    fn input_resolution(&self) -> usize {
        self.inner.input_resolution()
    }

    /// Side of the image it makes.
    #[getter]
    fn output_resolution(&self) -> usize {
        self.inner.output_resolution()
    }

    /// Super-resolves `features`, (C, R, R) or (B, C, R, R) float16/32/64, into float32 images
    /// (3, R_out, R_out) or (B, 3, R_out, R_out). Runs with the GIL released.
    fn apply<'py>(&self, py: Python<'py>, features: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyAny>> {
        guarded(|| {
            let f = float_array(features, "features", &["float16", "float32", "float64"])?;
            let (c, r) = (self.inner.in_channels(), self.inner.input_resolution());
            let (batched, n) = match f.shape.as_slice() {
                [b, ch, h, w] if (*ch, *h, *w) == (c, r, r) && *b >= 1 => (true, *b),
                [ch, h, w] if (*ch, *h, *w) == (c, r, r) => (false, 1),
                s => {
                    return Err(invalid(
                        "features",
                        format!("shape must be ({c}, {r}, {r}) or (B, {c}, {r}, {r}), got {s:?}"),
                    ))
                }
            };
            let out = py.detach(|| self.inner.apply(&f.data, n)).map_err(to_py)?;
            let ro = self.inner.output_resolution();
            let shape: Vec<usize> = if batched { vec![n, 3, ro, ro] } else { vec![3, ro, ro] };
            f32_array(py, &out, &shape)
        })
    }

    /// The network as the web page runs it: ``weights`` (float32, the packed vec4s), ``steps`` (in
    /// order: ``kernel`` entry point, ``layer`` (its eight u32 uniform fields), the ``src``, ``dst``
    /// and ``skip`` buffers by name, ``workgroups`` x and y; z is the images), the floats per image
    /// of each scratch buffer and image, and ``output`` (the buffer the image lands in).
    fn plan<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let plan = self.inner.plan();
        let flat: Vec<f32> = plan.packed.iter().flatten().copied().collect();
        let steps = PyList::empty(py);
        for step in &plan.steps {
            let d = PyDict::new(py);
            let l = &step.layer;
            d.set_item("kernel", step.kernel.name())?;
            let layer = [
                l.in_channels,
                l.out_channels,
                l.in_res,
                l.out_res,
                l.weights,
                l.bias,
                l.skip_channels,
                l.first_channel,
            ];
            d.set_item("layer", layer.to_vec())?;
            d.set_item("src", step.src.name())?;
            d.set_item("dst", step.dst.name())?;
            d.set_item("skip", step.skip.name())?;
            d.set_item("workgroups", step.workgroups.to_vec())?;
            steps.append(d)?;
        }
        let out = PyDict::new(py);
        out.set_item("weights", f32_array(py, &flat, &[flat.len()])?)?;
        out.set_item("steps", steps)?;
        out.set_item("scratch_floats", plan.scratch_floats)?;
        out.set_item("image_floats", plan.image_floats)?;
        out.set_item("output", plan.output.name())?;
        out.set_item("in_channels", self.inner.in_channels())?;
        out.set_item("input_resolution", self.inner.input_resolution())?;
        out.set_item("output_resolution", self.inner.output_resolution())?;
        Ok(out)
    }

    fn __repr__(&self) -> String {
        format!(
            "SuperRes(in_channels={}, {} -> {})",
            self.inner.in_channels(),
            self.inner.input_resolution(),
            self.inner.output_resolution()
        )
    }
}
