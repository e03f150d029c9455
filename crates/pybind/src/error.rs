//! Renderer errors → Python exceptions: bad input and bad files → ValueError, file-system
//! failures → OSError, device failures → RuntimeError.

use lp3d_renderer::Error;
use pyo3::exceptions::{PyOSError, PyRuntimeError, PyValueError};
use pyo3::PyErr;

pub fn to_py(e: Error) -> PyErr {
    match e {
        Error::InvalidInput { .. } | Error::Format { .. } => PyValueError::new_err(e.to_string()),
        Error::Io { .. } => PyOSError::new_err(e.to_string()),
        Error::Gpu(_) => PyRuntimeError::new_err(e.to_string()),
    }
}

pub fn invalid(field: &str, message: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(format!("{field}: {message}"))
}
