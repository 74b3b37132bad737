//! The one error type of the thermal core. Bindings map it to Python exceptions once.

use thiserror::Error;

/// Everything that can go wrong in the thermal core, each with a message that says what.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum ThermalError {
    /// A physical or numerical parameter outside its valid range.
    #[error("invalid parameter {name} = {value}: {reason}")]
    InvalidParameter {
        name: String,
        value: f64,
        reason: String,
    },
    /// Time step zero, negative or not finite.
    #[error("time step must be positive and finite, got dt = {0} s")]
    InvalidTimeStep(f64),
    /// An input series whose length does not match the number of steps (or of nodes).
    #[error("length mismatch for {name}: expected {expected}, got {got}")]
    LengthMismatch {
        name: String,
        expected: usize,
        got: usize,
    },
    /// A probe point that no element of the mesh contains.
    #[error("probe {index} at ({x:.6}, {y:.6}, {z:.6}) m lies outside the block")]
    ProbeOutside {
        index: usize,
        x: f64,
        y: f64,
        z: f64,
    },
    /// A face set name the mesh does not have.
    #[error("unknown face set {name:?}; the mesh has {known}")]
    UnknownFaceSet { name: String, known: String },
    /// The system matrix could not be Cholesky-factorised.
    #[error("the system matrix is not positive definite ({0}); check conductivity, capacity, convection and time step")]
    NotPositiveDefinite(String),
    /// A mesh that cannot be built or is degenerate.
    #[error("invalid mesh: {0}")]
    InvalidMesh(String),
    /// Failure inside the sparse linear algebra that is not a definiteness problem.
    #[error("sparse linear algebra failed: {0}")]
    LinearAlgebra(String),
    /// A bug: a panic caught at the boundary of the library.
    #[error("internal error in the thermal core (please report): {0}")]
    Internal(String),
}

/// Run `f`, turning a panic into [`ThermalError::Internal`] so that none crosses an FFI boundary.
pub fn catch_panic<T>(f: impl FnOnce() -> Result<T> + std::panic::UnwindSafe) -> Result<T> {
    std::panic::catch_unwind(f).unwrap_or_else(|payload| {
        let message = payload
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "unknown panic".to_string());
        Err(ThermalError::Internal(message))
    })
}

/// Result alias of the thermal core.
pub type Result<T> = std::result::Result<T, ThermalError>;

pub(crate) fn check_positive(name: &str, value: f64) -> Result<()> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(ThermalError::InvalidParameter {
            name: name.to_string(),
            value,
            reason: "must be positive and finite".to_string(),
        })
    }
}

pub(crate) fn check_non_negative(name: &str, value: f64) -> Result<()> {
    if value.is_finite() && value >= 0.0 {
        Ok(())
    } else {
        Err(ThermalError::InvalidParameter {
            name: name.to_string(),
            value,
            reason: "must be non-negative and finite".to_string(),
        })
    }
}

pub(crate) fn check_finite(name: &str, value: f64) -> Result<()> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(ThermalError::InvalidParameter {
            name: name.to_string(),
            value,
            reason: "must be finite".to_string(),
        })
    }
}
