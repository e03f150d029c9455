//! One error type for the crate. Every variant names what was wrong so the Python layer can
//! map it to a clear exception (`InvalidInput`/`Format` → ValueError, `Io` → OSError).

use std::fmt;
use std::path::PathBuf;

#[derive(Debug, Clone, PartialEq)]
pub enum Error {
    /// A value handed to the API is unusable; `field` names it (e.g. `camera[1]`, `resolution`).
    InvalidInput { field: String, message: String },
    /// A triplane file's contents are wrong (missing key, bad dtype, unknown version…).
    Format { path: PathBuf, field: String, message: String },
    /// The file system refused (missing file, unwritable directory…).
    Io { path: PathBuf, message: String },
    /// No adapter, out of device memory, a failed dispatch.
    Gpu(String),
}

pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    pub fn invalid(field: impl Into<String>, message: impl Into<String>) -> Self {
        Error::InvalidInput { field: field.into(), message: message.into() }
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::InvalidInput { field, message } => write!(f, "{field}: {message}"),
            // An empty field: the archive as a whole (not a zip, empty, too large).
            Error::Format { path, field, message } if field.is_empty() => {
                write!(f, "{}: {message}", path.display())
            }
            Error::Format { path, field, message } => {
                write!(f, "{}: key '{field}': {message}", path.display())
            }
            Error::Io { path, message } => write!(f, "{}: {message}", path.display()),
            Error::Gpu(message) => write!(f, "GPU error: {message}"),
        }
    }
}

impl std::error::Error for Error {}
