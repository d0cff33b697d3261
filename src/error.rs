//! The library's one error type. Every variant says *where* (a file, and a line and column when
//! the input is text, or the setting or stage) and *what* is wrong, in the terms of the inputs,
//! so the CLI can print it as one line. Command-line wording (flag names) belongs to the CLI.

use std::path::{Path, PathBuf};

/// A result with the library's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// An error from loading, validating, rendering or writing.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Reading or writing `path` failed; the operating system's error is the source.
    #[error("{}: {}", path.display(), io_words(source))]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// An input or output file is malformed or invalid. `at` is a (line, column) in text
    /// inputs, 1-based.
    #[error("{}{}: {message}", path.display(), at.map_or(String::new(), |(l, c)| format!(":{l}:{c}")))]
    File {
        path: PathBuf,
        at: Option<(usize, usize)>,
        message: String,
    },
    /// A setting outside its range: `name` as the library calls it (the CLI maps it to its
    /// flag).
    #[error("{name} must be {expected}, got {got}")]
    Setting {
        name: &'static str,
        expected: String,
        got: String,
    },
    /// A step of a longer job failed; `inner` says why.
    #[error("{stage}: {inner}")]
    Stage {
        stage: &'static str,
        inner: Box<Error>,
    },
    /// Work refused before it allocated: `what` would need `need` bytes, more than the
    /// `left` bytes of the memory budget (`crate::memory::budget`) allow; `bound` says which
    /// limit that is.
    #[error("{what} would need about {}, but only {} is left {bound}", size(*need), size(*left))]
    Memory {
        what: String,
        need: u64,
        left: u64,
        bound: String,
    },
    /// A request that is invalid whatever the files say (a job too large, nothing to fit).
    #[error("{0}")]
    Invalid(String),
}

/// A byte count for messages, in the largest unit that keeps it at least 1 (KiB to GiB).
pub fn size(bytes: u64) -> String {
    let b = bytes as f64;
    match bytes {
        0..1024 => format!("{bytes} bytes"),
        1024..1_048_576 => format!("{:.1} KiB", b / 1024.0),
        1_048_576..1_073_741_824 => format!("{:.1} MiB", b / 1_048_576.0),
        _ => format!("{:.1} GiB", b / 1_073_741_824.0),
    }
}

/// An I/O error worded for a person (the operating system's text without "(os error N)").
fn io_words(err: &std::io::Error) -> String {
    match err.kind() {
        std::io::ErrorKind::NotFound => "no such file or directory".to_string(),
        std::io::ErrorKind::PermissionDenied => "permission denied".to_string(),
        _ => err.to_string(),
    }
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

    /// An I/O error on `path`, keeping the operating system's error as the source.
    pub fn io(path: impl AsRef<Path>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.as_ref().to_path_buf(),
            source,
        }
    }
}
