//! `render`: one or a batch of camera views of a `Triplane`, every argument checked before any
//! GPU work.

use std::hash::BuildHasher;

use lp3d_renderer::baked::{MAX_FINE_SUBDIVISIONS, MAX_SUBDIVISIONS};
use lp3d_renderer::settings::{MAX_RESOLUTION, MAX_SAMPLES};
use lp3d_renderer::triplane::N_CHANNELS;
use lp3d_renderer::{Camera, Outputs, RenderOutput, RenderSettings, Skips};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use pyo3::exceptions::PyTypeError;

use crate::convert::{bool_arg, camera_array, f32_arg, f32_array, int_arg, names_arg, type_name, Arg};
use crate::device::{gpu, guarded};
use crate::error::{invalid, to_py};
use crate::superres::SuperRes;
use crate::triplane::Triplane;

/// Renders a triplane from one camera (25,) or a batch (B, 25).
///
/// Returns a dict of float32 arrays: ``features`` (32, R, R), ``rgb`` (3, R, R), ``depth``
/// (R, R), ``weights_sum`` (R, R), each with a leading B axis for a batch of cameras.
/// ``outputs`` restricts what is computed and returned. The defaults are exact EG3D semantics;
/// ``transmittance_threshold`` > 0 stops rays once their transmittance falls below it and
/// ``empty_threshold`` > 0 skips the importance pass of rays whose coarse opacity is below it;
/// their accuracy cost is in docs/performance.md, "Exact mode's skips". ``occupancy_epsilon`` > 0 skips samples
/// in the empty cells of the triplane's occupancy grid (baked at G = 64 on first use if it has
/// none), at most ``occupancy_epsilon`` opacity per skipped interval (docs/occupancy.md), in the
/// final composite; ``occupancy_coarse`` skips in the coarse pass too (faster; moves the
/// importance samples, so that part of the error is measured, not bounded).
/// ``baked_subdivisions`` = k > 0 skips the decoder: samples are looked up in the triplane's
/// baked field (``bake``; baked with k points per cell edge on first use), which holds
/// density and RGB only, so ``features`` cannot be asked for (docs/baked.md); it needs
/// ``occupancy_epsilon`` > 0. ``baked_fine_subdivisions`` > k makes it a two-level field: the
/// bricks a surface crosses get that many points per cell edge (docs/baked.md, "Two levels").
/// ``superres`` (an ``lp3d_render.SuperRes`` taking ``resolution``² feature images) adds ``image``
/// (3, R_out, R_out): the feature images super-resolved in the render's own command buffers.
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
                 occupancy_epsilon=Arg::Default(0.0), occupancy_coarse=Arg::Default(false),
                 baked_subdivisions=Arg::Default(0), baked_fine_subdivisions=Arg::Default(0), superres=None),
    text_signature = "(triplane, camera, resolution=128, depth_resolution=48, depth_resolution_importance=48, deterministic=True, seed=None, outputs=None, white_back=False, *, transmittance_threshold=0.0, empty_threshold=0.0, occupancy_epsilon=0.0, occupancy_coarse=False, baked_subdivisions=0, baked_fine_subdivisions=0, superres=None)"
)]
#[allow(clippy::too_many_arguments)]
// Long because: every argument is checked here, before any GPU work, one after another in the
// signature's order.
pub fn render<'py>(
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
    baked_subdivisions: Arg<'py, i64>,
    baked_fine_subdivisions: Arg<'py, i64>,
    superres: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    guarded(|| {
        let tri = Triplane::arg(triplane)?;
        let superres = match superres {
            Some(o) if !o.is_none() => Some(o.cast::<SuperRes>().map_err(|_| {
                PyTypeError::new_err(format!(
                    "superres: expected an lp3d_render.SuperRes, got {}",
                    type_name(o)
                ))
            })?),
            _ => None,
        };
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
                baked_subdivisions: int_arg(
                    &baked_subdivisions,
                    "baked_subdivisions",
                    0,
                    MAX_SUBDIVISIONS as i64,
                )? as u32,
                baked_fine_subdivisions: int_arg(
                    &baked_fine_subdivisions,
                    "baked_fine_subdivisions",
                    0,
                    MAX_FINE_SUBDIVISIONS as i64,
                )? as u32,
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
        let sr = superres.as_ref().map(|s| s.get().network());
        let (out, images) = py
            .detach(|| gpu.renderer.render_with_superres(&uploaded, &cameras, &settings, outputs, sr))
            .map_err(to_py)?;

        let dict = output_dict(py, &out, settings.resolution as usize, cameras.len(), batched)?;
        if let (Some(images), Some(sr)) = (images, sr) {
            let ro = sr.output_resolution();
            let shape: Vec<usize> = if batched { vec![cameras.len(), 3, ro, ro] } else { vec![3, ro, ro] };
            dict.set_item("image", f32_array(py, &images, &shape)?)?;
        }
        Ok(dict)
    })
}

/// The render's outputs as a dict of float32 arrays, (B, C, R, R) or (C, R, R) as the cameras
/// came batched or not (no C for depth and weights_sum).
fn output_dict<'py>(
    py: Python<'py>,
    out: &RenderOutput,
    r: usize,
    b: usize,
    batched: bool,
) -> PyResult<Bound<'py, PyDict>> {
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
}
