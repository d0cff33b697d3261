//! The library's one error type. Every variant says *where* (a file, and a line and column when
//! the input is text) and *what* is wrong, so the CLI can print it as one line.

use std::fmt;
use std::path::{Path, PathBuf};

/// A result with the library's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// An error from loading, validating, rendering or writing.
#[derive(Debug)]
pub enum Error {
    /// An input or output file is unreadable, malformed or invalid. `at` is a (line, column)
    /// in text inputs, 1-based.
    File {
        path: PathBuf,
        at: Option<(usize, usize)>,
        message: String,
    },
    /// A request that is invalid whatever the files say (bad option values, a job too large).
    Invalid(String),
}

impl Error {
    /// An error about `path`, with no position.
    pub fn file(path: impl AsRef<Path>, message: impl Into<String>) -> Self {
        Error::File {
            path: path.as_ref().to_path_buf(),
            at: None,
            message: message.into(),
        }
    }

    /// An error about `path` at a 1-based (line, column).
    pub fn file_at(
        path: impl AsRef<Path>,
        line: usize,
        col: usize,
        message: impl Into<String>,
    ) -> Self {
        Error::File {
            path: path.as_ref().to_path_buf(),
            at: Some((line, col)),
            message: message.into(),
        }
    }

    /// An I/O error on `path`, worded for a person.
    pub fn io(path: impl AsRef<Path>, err: std::io::Error) -> Self {
        let what = match err.kind() {
            std::io::ErrorKind::NotFound => "no such file or directory".to_string(),
            std::io::ErrorKind::PermissionDenied => "permission denied".to_string(),
            _ => err.to_string(),
        };
        Error::file(path, what)
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::File {
                path,
                at: Some((line, col)),
                message,
            } => {
                write!(f, "{}:{line}:{col}: {message}", path.display())
            }
            Error::File {
                path,
                at: None,
                message,
            } => write!(f, "{}: {message}", path.display()),
            Error::Invalid(message) => f.write_str(message),
        }
    }
}

impl std::error::Error for Error {}
