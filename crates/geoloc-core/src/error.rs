//! The one error type of geoloc-core.
//!
//! Every fallible public function returns [`Result<T>`]. Variants carry structured fields so
//! the Python bindings can map each onto a precise exception with a message that names the
//! offending argument. Geometry that is merely bad (too few points, a degenerate
//! configuration) is *not* an error for the solvers: they return a report with a reason.

use thiserror::Error;

/// Errors raised by geoloc-core on invalid input.
#[derive(Debug, Clone, PartialEq, Error)]
#[non_exhaustive]
pub enum GeolocError {
    /// An argument has the wrong size, shape or value.
    #[error("{name}: {reason}")]
    InvalidInput {
        /// The argument's name as the caller spells it.
        name: String,
        /// What is wrong, including what was expected.
        reason: String,
    },
    /// An argument holds NaN or ±∞.
    #[error("{name}[{index}] holds a non-finite value (NaN or inf)")]
    NonFinite {
        /// The argument's name.
        name: String,
        /// Index of the first offending item (of a batch), or of the value in a flat array.
        index: usize,
    },
    /// A matrix that must be a rotation (or a rigid transform) is not one within tolerance.
    #[error(
        "{name}{} is not a {what}: {reason}; project near-rotations first \
         (SO3::from_matrix_projected / geoloc.lie.so3_project)",
        .index.map_or(String::new(), |i| format!("[{i}]"))
    )]
    NotARotation {
        /// The argument's name.
        name: String,
        /// Index of the offending item in a batch (None for a single matrix).
        index: Option<usize>,
        /// "rotation" or "rigid transform".
        what: &'static str,
        /// The measured violation.
        reason: String,
    },
    /// A file could not be read or written (missing, a folder, not writable, disk full).
    #[error("{path}: {reason}")]
    Io {
        /// The file's path.
        path: String,
        /// What failed.
        reason: String,
    },
    /// A file's content is not what it must be (truncated, corrupt, another format version).
    #[error("{reason}")]
    Format {
        /// What is wrong, naming the file where known.
        reason: String,
    },
}

impl GeolocError {
    /// Shorthand for [`GeolocError::InvalidInput`].
    pub fn invalid(name: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::InvalidInput { name: name.into(), reason: reason.into() }
    }

    /// The same error reported for argument `name` at batch position `index`
    /// (used when a per-item check runs inside a batched call).
    #[must_use]
    pub fn at(self, name: &str, index: usize) -> Self {
        match self {
            Self::NotARotation { what, reason, .. } => {
                Self::NotARotation { name: name.to_owned(), index: Some(index), what, reason }
            }
            Self::NonFinite { .. } => Self::NonFinite { name: name.to_owned(), index },
            Self::InvalidInput { reason, .. } => Self::InvalidInput { name: format!("{name}[{index}]"), reason },
            other @ (Self::Io { .. } | Self::Format { .. }) => other,
        }
    }
}

impl GeolocError {
    /// The same error reported for a single (not batched) argument `name`: the name is
    /// replaced, and an index the error carries stays (a value's position, for NonFinite).
    #[must_use]
    pub fn named(self, name: &str) -> Self {
        match self {
            Self::NotARotation { what, reason, .. } => {
                Self::NotARotation { name: name.to_owned(), index: None, what, reason }
            }
            Self::NonFinite { index, .. } => Self::NonFinite { name: name.to_owned(), index },
            Self::InvalidInput { reason, .. } => Self::InvalidInput { name: name.to_owned(), reason },
            other @ (Self::Io { .. } | Self::Format { .. }) => other,
        }
    }
}

/// `Result` with [`GeolocError`].
pub type Result<T, E = GeolocError> = std::result::Result<T, E>;
