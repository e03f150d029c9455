//! Renderer errors → Python exceptions: bad input and bad files → ValueError, file-system
//! failures → OSError (or the subclass Python itself raises for that kind: FileNotFoundError,
//! PermissionError, IsADirectoryError, NotADirectoryError), device failures → RuntimeError.
//! The message is the error's text in every case.

use std::io::ErrorKind;

use lp3d_renderer::Error;
use pyo3::exceptions::{
    PyFileNotFoundError, PyIsADirectoryError, PyNotADirectoryError, PyOSError, PyPermissionError,
    PyRuntimeError, PyValueError,
};
use pyo3::PyErr;

pub fn to_py(e: Error) -> PyErr {
    let message = e.to_string();
    match e {
        Error::InvalidInput { .. } | Error::Format { .. } => PyValueError::new_err(message),
        Error::Io { kind, .. } => match kind {
            ErrorKind::NotFound => PyFileNotFoundError::new_err(message),
            ErrorKind::PermissionDenied => PyPermissionError::new_err(message),
            ErrorKind::IsADirectory => PyIsADirectoryError::new_err(message),
            ErrorKind::NotADirectory => PyNotADirectoryError::new_err(message),
            _ => PyOSError::new_err(message),
        },
        Error::Gpu(_) => PyRuntimeError::new_err(message),
    }
}

pub fn invalid(field: &str, message: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(format!("{field}: {message}"))
}
