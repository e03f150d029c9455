//! `look_at_camera`: a 25-float camera label from angles, the viewer's orbit camera.

use lp3d_renderer::camera::{FFHQ_FOCAL, FFHQ_PIVOT, FFHQ_RADIUS};
use lp3d_renderer::Camera;
use pyo3::prelude::*;

use crate::convert::{f32_array, finite_f32, float_arg, Arg};
use crate::error::invalid;

/// A look-at camera label (25,) from geometric angles in degrees: the renderer crate's
/// `Camera::look_at_camera`, the camera the viewer uses. Matches `lp3d.render.camera.look_at_camera`.
#[pyfunction]
#[pyo3(
    signature = (*, yaw_deg=Arg::Default(0.0), pitch_deg=Arg::Default(0.0), roll_deg=Arg::Default(0.0),
                 radius=Arg::Default(FFHQ_RADIUS), lookat=(FFHQ_PIVOT[0], FFHQ_PIVOT[1], FFHQ_PIVOT[2]),
                 focal=Arg::Default(FFHQ_FOCAL)),
    text_signature = "(*, yaw_deg=0.0, pitch_deg=0.0, roll_deg=0.0, radius=2.7, lookat=(0.0, 0.0, 0.2), focal=4.2647)"
)]
pub fn look_at_camera<'py>(
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
    let c =
        Camera::look_at_camera(yaw_deg, pitch_deg, roll_deg, radius, [lookat.0, lookat.1, lookat.2], focal);
    f32_array(py, &c.0, &[25])
}
