//! Conversions between numpy arrays and the core's slices, vectors and series.

use numpy::{IntoPyArray, PyArray2, PyArrayMethods, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use thermal_core::Series;

use crate::errors::LengthMismatchError;

/// A series of one value is a constant, of more a value per step.
pub(crate) fn series(values: &[f64]) -> Series<'_> {
    if values.len() == 1 {
        Series::Constant(values[0])
    } else {
        Series::Steps(values)
    }
}

/// A (n, k) array copied into a column-major vector.
pub(crate) fn column_major(a: &PyReadonlyArray2<'_, f64>) -> (Vec<f64>, usize, usize) {
    let view = a.as_array();
    let (n, k) = (view.shape()[0], view.shape()[1]);
    let mut data = Vec::with_capacity(n * k);
    for col in view.columns() {
        data.extend(col.iter().copied());
    }
    (data, n, k)
}

/// A column-major vector back into a (n, k) array.
pub(crate) fn from_column_major(
    py: Python<'_>,
    data: Vec<f64>,
    n: usize,
    k: usize,
) -> PyResult<Bound<'_, PyArray2<f64>>> {
    // column-major (n, k) is row-major (k, n): transpose into a fresh C-ordered array
    let t = data.into_pyarray(py).reshape([k, n])?;
    let owned = t.readonly().as_array().t().to_owned();
    Ok(PyArray2::from_owned_array(py, owned))
}

/// The rows of a (P, 3) array of points; `LengthMismatchError` naming `name` otherwise.
pub(crate) fn points(a: &PyReadonlyArray2<'_, f64>, name: &str) -> PyResult<Vec<[f64; 3]>> {
    let view = a.as_array();
    let shape = view.shape();
    if shape[1] != 3 {
        return Err(LengthMismatchError::new_err(format!(
            "{name} must be (P, 3), got {shape:?}"
        )));
    }
    Ok(view
        .rows()
        .into_iter()
        .map(|r| [r[0], r[1], r[2]])
        .collect())
}

/// Indices or counts given as int64: each must be `>= 0` (`ValueError` naming `name`).
pub(crate) fn non_negative(values: &[i64], name: &str) -> PyResult<Vec<usize>> {
    values
        .iter()
        .map(|&v| {
            usize::try_from(v)
                .map_err(|_| PyValueError::new_err(format!("{name} must be >= 0, got {v}")))
        })
        .collect()
}
