//! The Python exceptions of the bindings and the one mapping of [`ThermalError`] onto them.
//!
//! Every call into `thermal_core` goes through [`call`] or [`call_detached`]: a panic in the
//! core becomes [`ThermalError::Internal`] (`InternalError` in Python) instead of crossing the
//! FFI boundary, and every error is mapped by [`to_pyerr`], here and nowhere else.

use std::panic::UnwindSafe;

use pyo3::create_exception;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use thermal_core::error::{catch_panic, Result as CoreResult};
use thermal_core::ThermalError;

create_exception!(
    fleetbrake._ext,
    ThermalCoreError,
    PyValueError,
    "Base of every error of the thermal core."
);
create_exception!(
    fleetbrake._ext,
    InvalidParameterError,
    ThermalCoreError,
    "A parameter outside its valid range."
);
create_exception!(
    fleetbrake._ext,
    InvalidTimeStepError,
    ThermalCoreError,
    "Zero, negative or non-finite time step."
);
create_exception!(
    fleetbrake._ext,
    LengthMismatchError,
    ThermalCoreError,
    "Series of mismatched lengths."
);
create_exception!(
    fleetbrake._ext,
    ProbeOutsideError,
    ThermalCoreError,
    "A probe point outside the block."
);
create_exception!(
    fleetbrake._ext,
    UnknownFaceSetError,
    ThermalCoreError,
    "A face set the mesh does not have."
);
create_exception!(
    fleetbrake._ext,
    NotPositiveDefiniteError,
    ThermalCoreError,
    "A system matrix that is not positive definite."
);
create_exception!(
    fleetbrake._ext,
    MeshError,
    ThermalCoreError,
    "A mesh that cannot be built."
);
create_exception!(
    fleetbrake._ext,
    LinearAlgebraError,
    ThermalCoreError,
    "A failure of the sparse linear algebra."
);
create_exception!(
    fleetbrake._ext,
    InternalError,
    ThermalCoreError,
    "A bug in the thermal core."
);

/// The one mapping of core errors to Python exceptions.
pub(crate) fn to_pyerr(err: ThermalError) -> PyErr {
    let message = err.to_string();
    match err {
        ThermalError::InvalidParameter { .. } => InvalidParameterError::new_err(message),
        ThermalError::InvalidTimeStep(_) => InvalidTimeStepError::new_err(message),
        ThermalError::LengthMismatch { .. } => LengthMismatchError::new_err(message),
        ThermalError::ProbeOutside { .. } => ProbeOutsideError::new_err(message),
        ThermalError::UnknownFaceSet { .. } => UnknownFaceSetError::new_err(message),
        ThermalError::NotPositiveDefinite(_) => NotPositiveDefiniteError::new_err(message),
        ThermalError::InvalidMesh(_) => MeshError::new_err(message),
        ThermalError::LinearAlgebra(_) => LinearAlgebraError::new_err(message),
        ThermalError::Internal(_) => InternalError::new_err(message),
    }
}

/// Call the core with the GIL held (short calls): a panic becomes `InternalError`.
pub(crate) fn call<T>(f: impl FnOnce() -> CoreResult<T> + UnwindSafe) -> PyResult<T> {
    catch_panic(f).map_err(to_pyerr)
}

/// Call the core with the GIL released (long calls: meshing, factorising, stepping), so that
/// other Python threads run meanwhile; a panic becomes `InternalError`.
pub(crate) fn call_detached<T, F>(py: Python<'_>, f: F) -> PyResult<T>
where
    F: FnOnce() -> CoreResult<T> + UnwindSafe + Send,
    T: Send,
{
    py.detach(|| catch_panic(f)).map_err(to_pyerr)
}

/// Add the exception classes to the module.
pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("ThermalCoreError", py.get_type::<ThermalCoreError>())?;
    m.add(
        "InvalidParameterError",
        py.get_type::<InvalidParameterError>(),
    )?;
    m.add(
        "InvalidTimeStepError",
        py.get_type::<InvalidTimeStepError>(),
    )?;
    m.add("LengthMismatchError", py.get_type::<LengthMismatchError>())?;
    m.add("ProbeOutsideError", py.get_type::<ProbeOutsideError>())?;
    m.add("UnknownFaceSetError", py.get_type::<UnknownFaceSetError>())?;
    m.add(
        "NotPositiveDefiniteError",
        py.get_type::<NotPositiveDefiniteError>(),
    )?;
    m.add("MeshError", py.get_type::<MeshError>())?;
    m.add("LinearAlgebraError", py.get_type::<LinearAlgebraError>())?;
    m.add("InternalError", py.get_type::<InternalError>())?;
    Ok(())
}
