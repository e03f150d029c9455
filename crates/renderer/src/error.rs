//! One error type for the crate. Every variant names what was wrong so the Python layer can
//! map it to a clear exception (`InvalidInput`/`Format` → ValueError, `Io` → OSError, or the
//! subclass its [`io::ErrorKind`] names).

use std::fmt;
use std::io;
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Debug, Clone)]
pub enum Error {
    /// A value handed to the API is unusable; `field` names it (e.g. `camera[1]`, `resolution`).
    InvalidInput { field: String, message: String },
    /// A triplane file's contents are wrong (missing key, bad dtype, unknown version…).
    Format { path: PathBuf, field: String, message: String },
    /// The file system refused (missing file, unwritable directory…). `kind` is the refusal's
    /// [`io::ErrorKind`] and `source` the [`io::Error`] itself, where one came from the system
    /// (`None` for a refusal of lp3d's own, such as a FIFO where a file was expected); `message`
    /// is the text shown after the path. Build it with [`Error::io`] or [`Error::io_kind`].
    Io { path: PathBuf, kind: io::ErrorKind, message: String, source: Option<Arc<io::Error>> },
    /// No adapter, out of device memory, a failed dispatch.
    Gpu(String),
}

pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    pub fn invalid(field: impl Into<String>, message: impl Into<String>) -> Self {
        Error::InvalidInput { field: field.into(), message: message.into() }
    }

    /// The file system's `error` about `path`: its kind and text, and the error as the source.
    pub fn io(path: impl AsRef<Path>, error: io::Error) -> Self {
        Error::Io {
            path: path.as_ref().into(),
            kind: error.kind(),
            message: error.to_string(),
            source: Some(Arc::new(error)),
        }
    }

    /// A refusal about `path` of lp3d's own, with no system error behind it.
    pub fn io_kind(path: impl AsRef<Path>, kind: io::ErrorKind, message: impl Into<String>) -> Self {
        Error::Io { path: path.as_ref().into(), kind, message: message.into(), source: None }
    }
}

/// Equal when they say the same: an `Io` error's `source` is not compared (`io::Error` has no
/// equality; its kind and text are `kind` and `message`).
impl PartialEq for Error {
    fn eq(&self, other: &Self) -> bool {
        match (self, other) {
            (
                Error::InvalidInput { field: f1, message: m1 },
                Error::InvalidInput { field: f2, message: m2 },
            ) => f1 == f2 && m1 == m2,
            (
                Error::Format { path: p1, field: f1, message: m1 },
                Error::Format { path: p2, field: f2, message: m2 },
            ) => p1 == p2 && f1 == f2 && m1 == m2,
            (
                Error::Io { path: p1, kind: k1, message: m1, .. },
                Error::Io { path: p2, kind: k2, message: m2, .. },
            ) => p1 == p2 && k1 == k2 && m1 == m2,
            (Error::Gpu(m1), Error::Gpu(m2)) => m1 == m2,
            _ => false,
        }
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
            Error::Io { path, message, .. } => write!(f, "{}: {message}", path.display()),
            Error::Gpu(message) => write!(f, "GPU error: {message}"),
        }
    }
}

impl std::error::Error for Error {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Error::Io { source: Some(e), .. } => Some(e.as_ref()),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::error::Error as _;

    #[test]
    fn an_io_error_keeps_its_kind_and_source() {
        let path = Path::new("/no/such/dir/scene.npz");
        let system = std::fs::File::open(path).unwrap_err();
        let text = system.to_string();
        let e = Error::io(path, system);
        let Error::Io { kind, message, source, .. } = &e else { panic!("{e:?}") };
        assert_eq!(*kind, io::ErrorKind::NotFound);
        assert_eq!(*message, text);
        assert_eq!(source.as_ref().map(|s| s.kind()), Some(io::ErrorKind::NotFound));
        // The message is unchanged: the path, then the system's text.
        assert_eq!(e.to_string(), format!("/no/such/dir/scene.npz: {text}"));
        let inner = e.source().expect("an I/O error has its source");
        let inner = inner.downcast_ref::<io::Error>().expect("the source is the io::Error");
        assert_eq!(inner.kind(), io::ErrorKind::NotFound);
        assert_eq!(inner.raw_os_error(), Some(2)); // ENOENT
                                                   // A clone shares the source and is equal.
        let copy = e.clone();
        assert_eq!(copy, e);
        assert!(copy.source().is_some());
    }

    #[test]
    fn a_refusal_of_lp3ds_own_has_a_kind_and_no_source() {
        let e = Error::io_kind("a.npz", io::ErrorKind::InvalidInput, "is a FIFO");
        assert_eq!(e.to_string(), "a.npz: is a FIFO");
        assert!(matches!(e, Error::Io { kind: io::ErrorKind::InvalidInput, .. }));
        assert!(e.source().is_none());
        assert!(Error::Gpu("lost".into()).source().is_none());
    }

    #[test]
    fn io_errors_compare_by_path_kind_and_message() {
        let a = Error::io("a.npz", io::Error::new(io::ErrorKind::PermissionDenied, "denied"));
        // The same words with or without a source are equal; another kind or path is not.
        assert_eq!(a, Error::io_kind("a.npz", io::ErrorKind::PermissionDenied, "denied"));
        assert_ne!(a, Error::io_kind("a.npz", io::ErrorKind::Other, "denied"));
        assert_ne!(a, Error::io_kind("b.npz", io::ErrorKind::PermissionDenied, "denied"));
        assert_ne!(a, Error::Gpu("a.npz: denied".into()));
    }
}
