//! NumPy ↔ Rust conversion and validation of everything Python hands in. Every error names
//! the argument it is about.

use numpy::{PyArrayDyn, PyArrayMethods, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::error::invalid;

/// A float array read out of NumPy in C order.
pub struct FloatArray {
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
    pub was_f16: bool,
}

fn read<T: numpy::Element + Copy>(obj: &Bound<'_, PyAny>) -> Option<Vec<T>> {
    let arr = obj.cast::<PyArrayDyn<T>>().ok()?;
    let ro = arr.try_readonly().ok()?;
    Some(ro.as_array().iter().copied().collect())
}

/// Reads a float16/float32/float64 NumPy array (any memory layout).
/// `allow` lists accepted dtypes, e.g. `&["float16", "float32"]`.
pub fn float_array(obj: &Bound<'_, PyAny>, field: &str, allow: &[&str]) -> PyResult<FloatArray> {
    let untyped = obj
        .cast::<PyUntypedArray>()
        .map_err(|_| invalid(field, format!("expected a numpy array, got {}", type_name(obj))))?;
    let shape = untyped.shape().to_vec();
    let dtype = untyped.dtype().to_string();
    if !allow.contains(&dtype.as_str()) {
        return Err(invalid(field, format!("dtype must be one of {allow:?}, got {dtype}")));
    }
    let (data, was_f16) = match dtype.as_str() {
        "float16" => (read::<half::f16>(obj).map(|v| v.iter().map(|x| x.to_f32()).collect()), true),
        "float32" => (read::<f32>(obj), false),
        "float64" => (read::<f64>(obj).map(|v| v.iter().map(|&x| x as f32).collect()), false),
        _ => (None, false),
    };
    let data = data.ok_or_else(|| invalid(field, "could not read the array"))?;
    Ok(FloatArray { shape, data, was_f16 })
}

/// Reads a float64 view of a camera array ((25,) or (B, 25)); returns flat values and
/// whether a batch axis was given.
pub fn camera_array(obj: &Bound<'_, PyAny>) -> PyResult<(Vec<f64>, bool)> {
    let untyped = obj
        .cast::<PyUntypedArray>()
        .map_err(|_| invalid("camera", format!("expected a numpy array, got {}", type_name(obj))))?;
    let shape = untyped.shape().to_vec();
    let dtype = untyped.dtype().to_string();
    let batched = match shape.as_slice() {
        [25] => false,
        [b, 25] if *b >= 1 => true,
        _ => return Err(invalid("camera", format!("shape must be (25,) or (B, 25), got {shape:?}"))),
    };
    let data = match dtype.as_str() {
        "float64" => read::<f64>(obj),
        "float32" => read::<f32>(obj).map(|v| v.iter().map(|&x| x as f64).collect()),
        _ => return Err(invalid("camera", format!("dtype must be float32 or float64, got {dtype}"))),
    };
    Ok((data.ok_or_else(|| invalid("camera", "could not read the array"))?, batched))
}

pub fn expect_shape(a: &FloatArray, field: &str, shape: &[usize]) -> PyResult<()> {
    if a.shape != shape {
        return Err(invalid(field, format!("shape must be {shape:?}, got {:?}", a.shape)));
    }
    Ok(())
}

/// An integer setting in `[lo, hi]`, accepting any Python int (so negatives give a clear
/// ValueError rather than an OverflowError).
pub fn int_in(obj: &Bound<'_, PyAny>, field: &str, lo: i64, hi: i64) -> PyResult<u32> {
    if obj.is_instance_of::<pyo3::types::PyBool>() {
        return Err(invalid(field, "must be an int, got bool"));
    }
    let v: i64 =
        obj.extract().map_err(|_| invalid(field, format!("must be an int, got {}", type_name(obj))))?;
    if v < lo || v > hi {
        return Err(invalid(field, format!("must be in [{lo}, {hi}], got {v}")));
    }
    Ok(v as u32)
}

/// An integer setting in `[lo, hi]`.
pub fn in_range(v: i64, field: &str, lo: u32, hi: u32) -> PyResult<u32> {
    if v < lo as i64 || v > hi as i64 {
        return Err(invalid(field, format!("must be in [{lo}, {hi}], got {v}")));
    }
    Ok(v as u32)
}

pub fn finite_f32(v: f64, field: &str) -> PyResult<f32> {
    if !v.is_finite() {
        return Err(invalid(field, format!("must be finite, got {v}")));
    }
    Ok(v as f32)
}

pub fn type_name(obj: &Bound<'_, PyAny>) -> String {
    obj.get_type().name().map(|n| n.to_string()).unwrap_or_else(|_| "?".into())
}
