//! NumPy ↔ Rust conversion and validation of everything Python hands in. Every error names
//! the argument it is about.

use numpy::{PyArray1, PyArrayDyn, PyArrayMethods, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::exceptions::{PyOverflowError, PyTypeError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyString};

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

/// A scalar argument as Python gave it, or its default when it was left out. Taking the raw
/// object (instead of letting PyO3 convert it) lets the functions below validate every value
/// in one place, with messages naming the argument and the bad value: PyO3's own conversion
/// raises OverflowError for a large int, accepts `True` as 1 and names neither.
pub enum Arg<'py, T> {
    Default(T),
    Given(Bound<'py, PyAny>),
}

impl<'a, 'py, T> FromPyObject<'a, 'py> for Arg<'py, T> {
    type Error = PyErr;

    fn extract(obj: Borrowed<'a, 'py, PyAny>) -> PyResult<Self> {
        Ok(Arg::Given(obj.to_owned()))
    }
}

/// `obj`'s type and repr for an error message, e.g. `float 32.0` (shortened when long; a
/// repr that fails, such as that of an int too long to print, gives the type alone).
fn shown(obj: &Bound<'_, PyAny>) -> String {
    let repr = obj.repr().map(|r| r.to_string());
    match repr {
        Ok(r) if r.chars().count() > 60 => {
            format!("{} {}...", type_name(obj), r.chars().take(57).collect::<String>())
        }
        Ok(r) => format!("{} {r}", type_name(obj)),
        Err(_) => match obj.call_method0("bit_length").and_then(|b| b.extract::<u64>()) {
            Ok(bits) => format!("{} of {bits} bits", type_name(obj)),
            Err(_) => type_name(obj),
        },
    }
}

fn wrong_type(field: &str, expected: &str, obj: &Bound<'_, PyAny>) -> PyErr {
    PyTypeError::new_err(format!("{field}: must be {expected}, got {}", shown(obj)))
}

/// Python's bool and NumPy's bool_ (neither counts as a number here).
fn is_bool(obj: &Bound<'_, PyAny>) -> bool {
    obj.is_instance_of::<PyBool>()
        || (obj.get_type().module().is_ok_and(|m| m == "numpy")
            && obj.get_type().name().is_ok_and(|n| n == "bool_" || n == "bool"))
}

/// An integer argument in `[lo, hi]`: a Python or NumPy int (not a bool, not a float).
/// Wrong types are TypeErrors, values out of range (of any size) ValueErrors.
pub fn int_arg(arg: &Arg<'_, i64>, field: &str, lo: i64, hi: i64) -> PyResult<i64> {
    let out_of_range = |got: String| invalid(field, format!("must be an int in [{lo}, {hi}], got {got}"));
    let obj = match arg {
        Arg::Default(v) if (lo..=hi).contains(v) => return Ok(*v),
        Arg::Default(v) => return Err(out_of_range(v.to_string())),
        Arg::Given(obj) => obj,
    };
    if is_bool(obj) || !obj.hasattr("__index__").unwrap_or(false) {
        return Err(wrong_type(field, "an int", obj));
    }
    let index = obj.call_method0("__index__").map_err(|_| wrong_type(field, "an int", obj))?;
    match index.extract::<i64>() {
        Ok(v) if (lo..=hi).contains(&v) => Ok(v),
        Ok(v) => Err(out_of_range(v.to_string())),
        Err(_) => Err(out_of_range(shown(obj))),
    }
}

/// A number argument (Python or NumPy int or float; not a bool), finite.
pub fn float_arg(arg: &Arg<'_, f64>, field: &str) -> PyResult<f64> {
    let (v, obj) = match arg {
        Arg::Default(v) => (*v, None),
        Arg::Given(obj) => {
            if is_bool(obj) || obj.is_instance_of::<PyString>() {
                return Err(wrong_type(field, "a number", obj));
            }
            match obj.extract::<f64>() {
                Ok(v) => (v, Some(obj)),
                Err(e) if e.is_instance_of::<PyOverflowError>(obj.py()) => {
                    return Err(invalid(field, format!("must be finite, got {}", shown(obj))));
                }
                Err(_) => return Err(wrong_type(field, "a number", obj)),
            }
        }
    };
    if !v.is_finite() {
        let got = obj.map_or_else(|| format!("{v:?}"), shown);
        return Err(invalid(field, format!("must be finite, got {got}")));
    }
    Ok(v)
}

/// A number argument the GPU uses as float32: finite, and still finite in float32 (1e300 is a
/// finite float64 but Inf in float32).
pub fn f32_arg(arg: &Arg<'_, f64>, field: &str) -> PyResult<f32> {
    finite_f32(float_arg(arg, field)?, field)
}

/// A flag: Python's `True`/`False` or a NumPy bool (not `"yes"`, not `1`).
pub fn bool_arg(arg: &Arg<'_, bool>, field: &str) -> PyResult<bool> {
    match arg {
        Arg::Default(v) => Ok(*v),
        Arg::Given(obj) if is_bool(obj) => {
            obj.extract::<bool>().map_err(|_| wrong_type(field, "a bool", obj))
        }
        Arg::Given(obj) => Err(wrong_type(field, "a bool (True or False)", obj)),
    }
}

/// Most names a list argument may hold (the loop below must end even on an endless iterator).
const MAX_NAMES: usize = 64;

/// A list (any iterable) of strings, such as `outputs=["rgb", "depth"]`. A bare string is
/// refused: iterating it would give its letters.
pub fn names_arg(obj: &Bound<'_, PyAny>, field: &str) -> PyResult<Vec<String>> {
    let expected = "a list of strings such as ['rgb']";
    if obj.is_instance_of::<PyString>() {
        return Err(wrong_type(field, expected, obj));
    }
    let iter = obj.try_iter().map_err(|_| wrong_type(field, expected, obj))?;
    let mut names = Vec::new();
    for item in iter {
        let item = item?;
        if names.len() == MAX_NAMES {
            return Err(invalid(field, format!("holds more than {MAX_NAMES} names")));
        }
        let name = item
            .cast::<PyString>()
            .map_err(|_| PyTypeError::new_err(format!("{field}: must hold strings, got {}", shown(&item))))?;
        names.push(name.to_str()?.to_owned());
    }
    Ok(names)
}

/// A finite float32 from a float64 (both checks: 1e300 is finite only in float64).
pub fn finite_f32(v: f64, field: &str) -> PyResult<f32> {
    if !(v.is_finite() && (v as f32).is_finite()) {
        let why = if v.is_finite() { " (it overflows float32)" } else { "" };
        return Err(invalid(field, format!("must be finite, got {v:?}{why}")));
    }
    Ok(v as f32)
}

pub fn type_name(obj: &Bound<'_, PyAny>) -> String {
    obj.get_type().name().map(|n| n.to_string()).unwrap_or_else(|_| "?".into())
}

/// A float32 NumPy array of `shape` holding `data` (C order), for results handed back to Python.
pub fn f32_array<'py>(py: Python<'py>, data: &[f32], shape: &[usize]) -> PyResult<Bound<'py, PyAny>> {
    Ok(PyArray1::from_slice(py, data).reshape(shape)?.into_any())
}
