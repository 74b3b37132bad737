//! Thin pyo3 bindings of `thermal_core`, the Python module `fleetbrake._ext`: convert
//! arguments, call the core with the GIL released, map errors once. Defaults, docstrings and
//! validation of user input live in Python (`python/fleetbrake/model/thermal.py` and
//! `python/fleetbrake/model/rom.py`); the stubs are `python/fleetbrake/_ext.pyi`.
//!
//! - [`errors`]: the exception classes and the one mapping of the core's error enum onto them
//!   (no panic of the core reaches Python: it becomes `InternalError`);
//! - [`convert`]: numpy arrays to and from the core's slices, vectors and series;
//! - [`model`]: the finite-element model (`ThermalModel`);
//! - [`rom`]: the reduced model (`rom_*` functions).

mod convert;
mod errors;
mod estimator;
mod model;
mod rom;

use pyo3::prelude::*;

/// The module: each binding module adds what it defines (a new one: `mod x;` above and
/// `x::register(m)?;` here).
#[pymodule]
fn _ext(m: &Bound<'_, PyModule>) -> PyResult<()> {
    errors::register(m)?;
    estimator::register(m)?;
    model::register(m)?;
    rom::register(m)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
