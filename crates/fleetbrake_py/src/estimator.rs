//! The virtual sensor's kernel: the Kalman filter and smoother of many wagons' problems at
//! once, wagons in parallel, with the GIL released (see `fleetbrake.model.estimator`).

use std::borrow::Cow;

use numpy::{IntoPyArray, PyArrayMethods, PyReadonlyArray1};
use pyo3::exceptions::PyKeyError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use thermal_core::estimator::{
    run_many, Eigen, Estimates, Noise, Outputs, Problem, Settings, Switching, Transition,
};

use crate::errors::call_detached;

/// Item `key` of a problem's dictionary (`KeyError` naming it when absent).
fn item<'py>(d: &Bound<'py, PyDict>, key: &str) -> PyResult<Bound<'py, PyAny>> {
    d.get_item(key)?
        .ok_or_else(|| PyKeyError::new_err(format!("estimator problem: no {key:?}")))
}

fn floats(d: &Bound<'_, PyDict>, key: &str) -> PyResult<Vec<f64>> {
    let a = item(d, key)?.extract::<PyReadonlyArray1<'_, f64>>()?;
    Ok(a.as_array().iter().copied().collect())
}

/// A problem's per-step series, held (read-only) while the kernel borrows them.
struct SeriesArrays<'py> {
    index: PyReadonlyArray1<'py, u32>,
    w: PyReadonlyArray1<'py, f64>,
    reading: PyReadonlyArray1<'py, f64>,
}

fn series_arrays<'py>(d: &Bound<'py, PyDict>) -> PyResult<SeriesArrays<'py>> {
    Ok(SeriesArrays {
        index: item(d, "index")?.extract()?,
        w: item(d, "w")?.extract()?,
        reading: item(d, "reading_c")?.extract()?,
    })
}

/// One problem from the dictionary `fleetbrake.model.estimator` makes of it (flat arrays;
/// the per-step series borrowed from `series`, C-contiguous, without a copy).
fn problem<'a>(d: &Bound<'_, PyDict>, series: &'a SeriesArrays<'_>) -> PyResult<Problem<'a>> {
    let order: usize = item(d, "order")?.extract()?;
    let diagonal: Vec<bool> = item(d, "diagonal")?.extract()?;
    // per transition, whether the cylinder is applied over it (absent: none)
    let applied: Vec<bool> = match d.get_item("applied")? {
        Some(v) if !v.is_none() => v.extract()?,
        _ => Vec::new(),
    };
    let (a, gamma, lag_row) = (floats(d, "a")?, floats(d, "gamma")?, floats(d, "lag_row")?);
    let (phi, q_unit, q_gap) = (floats(d, "phi")?, floats(d, "q_unit")?, floats(d, "q_gap")?);
    let (lag_a, lag_b1, lag_power) = (
        floats(d, "lag_a")?,
        floats(d, "lag_b1")?,
        floats(d, "lag_power")?,
    );
    let r = order;
    let k = diagonal.len();
    // per transition, the braking power P_b's decay and noise (absent or None: no P_b)
    let optional = |key: &str| -> PyResult<Option<Vec<f64>>> {
        match d.get_item(key)? {
            Some(v) if !v.is_none() => Ok(Some(
                v.extract::<PyReadonlyArray1<'_, f64>>()?
                    .as_array()
                    .iter()
                    .copied()
                    .collect(),
            )),
            _ => Ok(None),
        }
    };
    let (brake_phi, brake_q) = (optional("brake_phi")?, optional("brake_q")?);
    let brake = brake_phi.is_some();
    // per transition, r variances of the modal coordinates (absent or empty: none)
    let q_modes = match d.get_item("q_modes")? {
        Some(v) if !v.is_none() => v
            .extract::<PyReadonlyArray1<'_, f64>>()?
            .as_array()
            .iter()
            .copied()
            .collect(),
        _ => Vec::new(),
    };
    // per transition, a = Q diag(e) Qᵀ as `prepare` made it (absent or None: the kernel
    // steps a dense transition dense)
    let (eigenvectors, eigenvalues) = (optional("eigenvectors")?, optional("eigenvalues")?);
    let sizes = [
        eigenvectors.is_some() == eigenvalues.is_some(),
        eigenvectors.as_ref().is_none_or(|v| v.len() == k * r * r),
        eigenvalues.as_ref().is_none_or(|v| v.len() == k * r),
        q_modes.is_empty() || q_modes.len() == k * r,
        a.len() == k * r * r,
        gamma.len() == k * r,
        lag_row.len() == k * r,
        phi.len() == k,
        q_unit.len() == k,
        q_gap.len() == k,
        lag_a.len() == k,
        lag_b1.len() == k,
        lag_power.len() == k,
        applied.is_empty() || applied.len() == k,
        brake_phi.as_ref().is_none_or(|v| v.len() == k),
        brake_q.as_ref().map_or(!brake, |v| v.len() == k),
    ];
    if sizes.iter().any(|ok| !ok) {
        return Err(crate::errors::LengthMismatchError::new_err(format!(
            "estimator problem: the transition arrays do not describe {k} transitions of order {r}"
        )));
    }
    let transitions = (0..k)
        .map(|t| {
            let at = a[t * r * r..(t + 1) * r * r].to_vec();
            Transition {
                diagonal: diagonal[t],
                e: (0..r).map(|i| at[i * r + i]).collect(),
                a: at,
                gamma: gamma[t * r..(t + 1) * r].to_vec(),
                phi: phi[t],
                q_unit: q_unit[t],
                q_gap: q_gap[t],
                q_modes: if q_modes.is_empty() {
                    Vec::new()
                } else {
                    q_modes[t * r..(t + 1) * r].to_vec()
                },
                lag_a: lag_a[t],
                lag_b1: lag_b1[t],
                lag_row: lag_row[t * r..(t + 1) * r].to_vec(),
                lag_power: lag_power[t],
                applied: applied.get(t).copied().unwrap_or(false),
                brake_phi: brake_phi.as_ref().map_or(1.0, |v| v[t]),
                brake_q: brake_q.as_ref().map_or(0.0, |v| v[t]),
                eigen: match (&eigenvectors, &eigenvalues) {
                    (Some(q), Some(e)) if !diagonal[t] => Some(Eigen {
                        q: q[t * r * r..(t + 1) * r * r].to_vec(),
                        e: e[t * r..(t + 1) * r].to_vec(),
                    }),
                    _ => None,
                },
            }
        })
        .collect();
    Ok(Problem {
        order,
        lag: item(d, "lag")?.extract()?,
        brake,
        t_ref_c: item(d, "t_ref_c")?.extract()?,
        transitions,
        index: Cow::Borrowed(series.index.as_slice()?),
        w: Cow::Borrowed(series.w.as_slice()?),
        power_noise: match d.get_item("power_noise")? {
            Some(v) if !v.is_none() => Cow::Owned(
                v.extract::<PyReadonlyArray1<'_, f64>>()?
                    .as_array()
                    .iter()
                    .copied()
                    .collect(),
            ),
            _ => Cow::Owned(Vec::new()),
        },
        reading_c: Cow::Borrowed(series.reading.as_slice()?),
        c_probe: floats(d, "c_probe")?,
        c_mean: floats(d, "c_mean")?,
        c_nodes: floats(d, "c_nodes")?,
        x0: floats(d, "x0")?,
        cov0: floats(d, "cov0")?,
        p_prior_unit: item(d, "p_prior_unit")?.extract()?,
        gap_dir: floats(d, "gap_dir")?,
    })
}

fn put_estimates<'py>(
    py: Python<'py>,
    d: &Bound<'py, PyDict>,
    prefix: &str,
    e: Option<Estimates>,
) -> PyResult<()> {
    let names = [
        "mean_c",
        "mean_sd_k",
        "max_c",
        "max_sd_k",
        "power_w",
        "power_sd_w",
    ];
    match e {
        Some(e) => {
            let values = [
                e.mean_c,
                e.mean_sd_k,
                e.max_c,
                e.max_sd_k,
                e.power_w,
                e.power_sd_w,
            ];
            for (name, v) in names.iter().zip(values) {
                d.set_item(format!("{prefix}{name}"), v.into_pyarray(py))?;
            }
        }
        None => {
            for name in names {
                d.set_item(format!("{prefix}{name}"), py.None())?;
            }
        }
    }
    Ok(())
}

/// The outputs of one problem as the dictionary of `KernelOutputs`' fields.
fn outputs<'py>(py: Python<'py>, out: Outputs, n: usize) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    put_estimates(py, &d, "", Some(out.filtered))?;
    put_estimates(py, &d, "smoothed_", out.smoothed)?;
    d.set_item("innovation_k", out.innovation_k.into_pyarray(py))?;
    d.set_item("innovation_var_k2", out.innovation_var_k2.into_pyarray(py))?;
    d.set_item(
        "predicted_reading_c",
        out.predicted_reading_c.into_pyarray(py),
    )?;
    d.set_item("log_likelihood", out.log_likelihood)?;
    d.set_item("updates", out.updates)?;
    d.set_item("frozen_steps", out.frozen_steps)?;
    d.set_item("manoeuvre", out.manoeuvre.into_pyarray(py))?;
    d.set_item("manoeuvre_steps", out.manoeuvre_steps)?;
    d.set_item("smoother_frozen_steps", out.smoother_frozen_steps)?;
    d.set_item("memo_steps", out.memo_steps)?;
    d.set_item("final_state", out.final_state.into_pyarray(py))?;
    d.set_item("final_cov", out.final_cov.into_pyarray(py).reshape([n, n])?)?;
    Ok(d)
}

/// Filter (and smooth) every problem (dictionaries of flat arrays) with the same noise and
/// settings; wagons in parallel, the GIL released. Returns one dictionary per problem.
/// `switching`: (σ_q, window in steps, on, off, hold, the smoother's lead in steps, σ_q over
/// a step with the cylinder applied) of the power noise's two modes, or None for σ_w at every
/// step. `manoeuvre_tolerances`: (filter, smoother) steady tolerances for the steps in the
/// manoeuvre mode, or None for `steady_tolerance` and `smoother_tolerance` there too.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
#[pyo3(signature = (problems, measurement_k, power_w_per_sqrt_s, smooth, steady_tolerance, smoother_tolerance, checkpoint_steps, outputs_wanted, switching=None, manoeuvre_tolerances=None))]
fn estimator_run<'py>(
    py: Python<'py>,
    problems: &Bound<'py, PyList>,
    measurement_k: f64,
    power_w_per_sqrt_s: f64,
    smooth: bool,
    steady_tolerance: f64,
    smoother_tolerance: f64,
    checkpoint_steps: usize,
    outputs_wanted: bool,
    switching: Option<(f64, f64, f64, f64, f64, usize, f64)>,
    manoeuvre_tolerances: Option<(f64, f64)>,
) -> PyResult<Vec<Bound<'py, PyDict>>> {
    let dicts: Vec<Bound<'py, PyDict>> = problems
        .iter()
        .map(|p| Ok(p.cast::<PyDict>()?.clone()))
        .collect::<PyResult<_>>()?;
    let arrays: Vec<SeriesArrays<'py>> =
        dicts.iter().map(series_arrays).collect::<PyResult<_>>()?;
    let problems: Vec<Problem<'_>> = dicts
        .iter()
        .zip(&arrays)
        .map(|(d, a)| problem(d, a))
        .collect::<PyResult<_>>()?;
    let noise = Noise {
        measurement_k,
        power_w_per_sqrt_s,
        switching: switching.map(|(q, window, on, off, hold, lead, applied)| Switching {
            quiet_w_per_sqrt_s: q,
            window_steps: window,
            on_sigma: on,
            off_sigma: off,
            hold_power_sigma: hold,
            smoother_lead_steps: lead,
            applied_w_per_sqrt_s: applied,
        }),
    };
    let settings = Settings {
        smooth,
        steady_tolerance,
        smoother_tolerance,
        manoeuvre_tolerances,
        checkpoint_steps,
        outputs: outputs_wanted,
        replay: true,
    };
    let sizes: Vec<usize> = problems.iter().map(Problem::n_state).collect();
    let results = call_detached(py, || run_many(&problems, noise, &settings))?;
    results
        .into_iter()
        .zip(sizes)
        .map(|(out, n)| outputs(py, out, n))
        .collect()
}

/// Add the estimator's functions to the module.
pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(estimator_run, m)?)?;
    Ok(())
}
