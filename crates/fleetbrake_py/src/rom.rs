//! The reduced model: modal stepping of many events, exact propagators, switched step systems
//! (see `fleetbrake.model.rom`).

use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2,
    PyReadonlyArray3,
};
use std::panic::AssertUnwindSafe;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use thermal_core::rom::{
    chain_step_convection_into, exact_propagator, step_systems, step_systems_into, AnchorRule,
    ChainModel, ChainSteps, ModalStepper, Propagators,
};
use thermal_core::ThermalError;

use crate::convert::non_negative;
use crate::errors::{call, call_detached, to_pyerr};

/// Three arrays handed back to Python.
type ArrayTriple<'py> = (
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
);

/// Two vectors handed back to Python.
type VectorPair<'py> = (Bound<'py, PyArray1<f64>>, Bound<'py, PyArray1<f64>>);

/// Step a reduced model (modal form, nominal convection, exact in time) over many events:
/// flux (E, S), drive (T_amb - T_ref) (E, S) or (E, 1), t_ref (E). Returns (probe
/// (E (S+1), P), face mean (E, S+1), face max (E, S+1)).
#[pyfunction]
#[allow(clippy::too_many_arguments)]
fn rom_simulate_batch<'py>(
    py: Python<'py>,
    lam: PyReadonlyArray1<'py, f64>,
    b_q: PyReadonlyArray1<'py, f64>,
    b_a: PyReadonlyArray1<'py, f64>,
    c_out: PyReadonlyArray2<'py, f64>,
    n_probes: usize,
    dt_s: f64,
    flux: PyReadonlyArray2<'py, f64>,
    drive: PyReadonlyArray2<'py, f64>,
    t_ref: PyReadonlyArray1<'py, f64>,
) -> PyResult<ArrayTriple<'py>> {
    let c: Vec<f64> = c_out.as_array().iter().copied().collect();
    let (lam, b_q, b_a) = (lam.as_slice()?, b_q.as_slice()?, b_a.as_slice()?);
    let stepper = call(|| ModalStepper::new(lam, b_q, b_a, c, n_probes, dt_s))?;
    let shape = flux.as_array().shape().to_vec();
    let (n_events, n_steps) = (shape[0], shape[1]);
    // C-contiguous (the Python side makes them so): read in place, no copies
    let (flux_s, drive_s, t_ref_s) = (flux.as_slice()?, drive.as_slice()?, t_ref.as_slice()?);
    let out = call_detached(py, || {
        stepper.simulate_batch(flux_s, drive_s, t_ref_s, n_steps)
    })?;
    let rows = n_steps + 1;
    Ok((
        out.probe_c
            .into_pyarray(py)
            .reshape([n_events * rows, n_probes])?,
        out.face_mean_c.into_pyarray(py).reshape([n_events, rows])?,
        out.face_max_c.into_pyarray(py).reshape([n_events, rows])?,
    ))
}

/// The exact propagator (e, g) of modes with rates `lam` over a step of `dt_s`: e =
/// exp(-lam dt), g = (1 - e) / lam.
#[pyfunction]
fn rom_exact_propagator<'py>(
    py: Python<'py>,
    lam: PyReadonlyArray1<'py, f64>,
    dt_s: f64,
) -> PyResult<VectorPair<'py>> {
    if !(dt_s.is_finite() && dt_s > 0.0) {
        return Err(to_pyerr(ThermalError::InvalidTimeStep(dt_s)));
    }
    let lam = lam.as_slice()?;
    let (e, g) = call(|| Ok(exact_propagator(lam, dt_s)))?;
    Ok((e.into_pyarray(py), g.into_pyarray(py)))
}

/// One run of a reduced model through switching step systems: propagators e, g (K, r),
/// q (K, r, r), rotated (K); per step the propagator index and repeat count (S), the modal
/// input u (S, r); xi0 (r); output rows c (n_out, r). Returns (C xi (S+1, n_out), final xi).
#[pyfunction]
#[allow(clippy::too_many_arguments)]
#[allow(clippy::type_complexity)]
fn rom_simulate_switched<'py>(
    py: Python<'py>,
    e: PyReadonlyArray2<'py, f64>,
    g: PyReadonlyArray2<'py, f64>,
    q: PyReadonlyArray3<'py, f64>,
    rotated: Vec<bool>,
    index: PyReadonlyArray1<'py, i64>,
    repeats: PyReadonlyArray1<'py, i64>,
    u: PyReadonlyArray2<'py, f64>,
    xi0: PyReadonlyArray1<'py, f64>,
    c: PyReadonlyArray2<'py, f64>,
) -> PyResult<(Bound<'py, PyArray2<f64>>, Bound<'py, PyArray1<f64>>)> {
    let order = xi0.len()?;
    let (e, g, q) = (
        e.as_slice()?.to_vec(),
        g.as_slice()?.to_vec(),
        q.as_slice()?.to_vec(),
    );
    let props = call(|| Propagators::new(order, e, g, q, rotated))?;
    let index = non_negative(index.as_slice()?, "propagator index")?;
    let repeats = non_negative(repeats.as_slice()?, "repeats")?
        .into_iter()
        .map(|v| {
            u32::try_from(v).map_err(|_| PyValueError::new_err(format!("repeats too large: {v}")))
        })
        .collect::<PyResult<Vec<u32>>>()?;
    let n_out = c.as_array().shape()[0];
    let (u_s, xi_s, c_s) = (u.as_slice()?, xi0.as_slice()?, c.as_slice()?);
    let (y, xi) = call_detached(py, || props.simulate(&index, &repeats, u_s, xi_s, c_s))?;
    let steps = y.len() / n_out.max(1);
    Ok((
        y.into_pyarray(py).reshape([steps, n_out])?,
        xi.into_pyarray(py),
    ))
}

/// Indices given as int64 (`-1`: none, as `usize::MAX`), each otherwise `>= 0`.
fn optional_indices(values: &[i64], name: &str) -> PyResult<Vec<usize>> {
    values
        .iter()
        .map(|&v| match v {
            -1 => Ok(usize::MAX),
            v if v >= 0 => Ok(v as usize),
            v => Err(PyValueError::new_err(format!(
                "{name} must be >= -1, got {v}"
            ))),
        })
        .collect()
}

/// A span's chain (see `fleetbrake.simulation.batched`): propagators e, g (K, r), q (K, r,
/// r), rotated (K); the model's b_flux (r), b_faces (F, r), c_out (n_out, r), n_probes;
/// per step flux, ambient (T), h (T, F), propagator (T); per piece a, b, dt (P), step
/// offsets (P+1), coarse grid positions `at` with offsets (P+1); per segment the window's
/// continuation piece (-1: none) and window length (J); per sample trusted readings and
/// ambient (n); the anchoring rule; `windows`: one flag per window output, those wanted
/// (None: every output; `thermal_core::rom::Propagators::simulate_chain_reading`). Returns
/// (sensor, contact mean, contact max (n), anchor codes (J), shifts (J), references (J),
/// window sensor, mean, max (sum of lengths)).
#[pyfunction]
#[pyo3(signature = (e, g, q, rotated, b_flux, b_faces, c_out, n_probes, step_flux, step_ambient, step_h, step_prop, piece_a, piece_b, piece_dt, step_off, at, at_off, seg_cont, seg_window, trusted, ambient, anchor_s, anchor_min_readings, window_s, tolerance_k, lag_tau_s, windows=None))]
#[allow(clippy::too_many_arguments)]
#[allow(clippy::type_complexity)]
fn rom_simulate_chain<'py>(
    py: Python<'py>,
    e: PyReadonlyArray2<'py, f64>,
    g: PyReadonlyArray2<'py, f64>,
    q: PyReadonlyArray3<'py, f64>,
    rotated: Vec<bool>,
    b_flux: PyReadonlyArray1<'py, f64>,
    b_faces: PyReadonlyArray2<'py, f64>,
    c_out: PyReadonlyArray2<'py, f64>,
    n_probes: usize,
    step_flux: PyReadonlyArray1<'py, f64>,
    step_ambient: PyReadonlyArray1<'py, f64>,
    step_h: PyReadonlyArray2<'py, f64>,
    step_prop: PyReadonlyArray1<'py, i64>,
    piece_a: PyReadonlyArray1<'py, i64>,
    piece_b: PyReadonlyArray1<'py, i64>,
    piece_dt: PyReadonlyArray1<'py, f64>,
    step_off: PyReadonlyArray1<'py, i64>,
    at: PyReadonlyArray1<'py, f64>,
    at_off: PyReadonlyArray1<'py, i64>,
    seg_cont: PyReadonlyArray1<'py, i64>,
    seg_window: PyReadonlyArray1<'py, i64>,
    trusted: PyReadonlyArray1<'py, f64>,
    ambient: PyReadonlyArray1<'py, f64>,
    anchor_s: usize,
    anchor_min_readings: usize,
    window_s: usize,
    tolerance_k: f64,
    lag_tau_s: Option<f64>,
    windows: Option<PyReadonlyArray1<'py, bool>>,
) -> PyResult<(Vec<Bound<'py, PyArray1<f64>>>, Bound<'py, PyArray1<u8>>)> {
    let order = b_flux.len()?;
    let (e, g, q) = (
        e.as_slice()?.to_vec(),
        g.as_slice()?.to_vec(),
        q.as_slice()?.to_vec(),
    );
    let props = call(|| Propagators::new(order, e, g, q, rotated))?;
    let prop = non_negative(step_prop.as_slice()?, "propagator index")?;
    let piece_a = non_negative(piece_a.as_slice()?, "piece start")?;
    let piece_b = non_negative(piece_b.as_slice()?, "piece end")?;
    let step_off = non_negative(step_off.as_slice()?, "step offsets")?;
    let at_off = non_negative(at_off.as_slice()?, "grid offsets")?;
    let seg_cont = optional_indices(seg_cont.as_slice()?, "window continuation")?;
    let seg_window = non_negative(seg_window.as_slice()?, "window length")?;
    let model = ChainModel {
        b_flux: b_flux.as_slice()?,
        b_faces: b_faces.as_slice()?,
        c: c_out.as_slice()?,
        n_probes,
    };
    let steps = ChainSteps {
        flux: step_flux.as_slice()?,
        ambient: step_ambient.as_slice()?,
        h: step_h.as_slice()?,
        prop: &prop,
        piece_a: &piece_a,
        piece_b: &piece_b,
        piece_dt: piece_dt.as_slice()?,
        step_off: &step_off,
        at: at.as_slice()?,
        at_off: &at_off,
        seg_cont: &seg_cont,
        seg_window: &seg_window,
    };
    let rule = AnchorRule {
        anchor_s,
        anchor_min_readings,
        window_s,
        tolerance_k,
        lag_tau_s,
    };
    let (trusted, ambient) = (trusted.as_slice()?, ambient.as_slice()?);
    let windows = windows.as_ref().map(|w| w.as_slice()).transpose()?;
    let out = call_detached(py, || {
        props.simulate_chain_reading(&model, &steps, trusted, ambient, &rule, windows)
    })?;
    let floats = vec![
        out.sensor_c.into_pyarray(py),
        out.contact_mean_c.into_pyarray(py),
        out.contact_max_c.into_pyarray(py),
        out.shift_k.into_pyarray(py),
        out.reference_c.into_pyarray(py),
        out.window_sensor_c.into_pyarray(py),
        out.window_mean_c.into_pyarray(py),
        out.window_max_c.into_pyarray(py),
    ];
    Ok((floats, out.anchor.into_pyarray(py)))
}

/// The distinct step systems of a chain's steps (`thermal_core::rom::step_systems`): h (T,
/// F) per step, h_nominal (F), piece_dt (P), step_off (P+1). Returns (dh (K, F), dt (K),
/// each step's system (T)).
#[pyfunction]
#[allow(clippy::type_complexity)]
fn rom_chain_systems<'py>(
    py: Python<'py>,
    h: PyReadonlyArray2<'py, f64>,
    h_nominal: PyReadonlyArray1<'py, f64>,
    piece_dt: PyReadonlyArray1<'py, f64>,
    step_off: PyReadonlyArray1<'py, i64>,
) -> PyResult<(
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<i64>>,
)> {
    let faces = h_nominal.len()?;
    if h.as_array().shape()[1] != faces {
        return Err(PyValueError::new_err(format!(
            "step convection has {} face sets, h_nominal {faces}",
            h.as_array().shape()[1]
        )));
    }
    let step_off = non_negative(step_off.as_slice()?, "step offsets")?;
    let (h_s, h0, dt) = (h.as_slice()?, h_nominal.as_slice()?, piece_dt.as_slice()?);
    let out = call_detached(py, || step_systems(h_s, h0, dt, &step_off))?;
    let systems = out.dt_s.len();
    let index: Vec<i64> = out.index.iter().map(|&k| k as i64).collect();
    Ok((
        out.dh.into_pyarray(py).reshape([systems, faces])?,
        out.dt_s.into_pyarray(py),
        index.into_pyarray(py),
    ))
}

/// A chain's convection per step and its step systems in one pass
/// (`thermal_core::rom::chain_step_convection`, then `step_systems`): `samples`, each face
/// set's per-sample convection on each source (face-major, F x S arrays), `gather` (T),
/// `step_off` (P+1), `piece_dt` (P), `h_nominal` (F), `quantum`. Returns (h (T, F), dh (K,
/// F), dt (K), each step's system (T)).
#[pyfunction]
#[allow(clippy::too_many_arguments)]
#[allow(clippy::type_complexity)]
fn rom_chain_convection<'py>(
    py: Python<'py>,
    samples: Vec<PyReadonlyArray1<'py, f64>>,
    gather: PyReadonlyArray1<'py, i64>,
    step_off: PyReadonlyArray1<'py, i64>,
    piece_dt: PyReadonlyArray1<'py, f64>,
    h_nominal: PyReadonlyArray1<'py, f64>,
    quantum: f64,
) -> PyResult<(
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<i64>>,
)> {
    if !(quantum.is_finite() && quantum > 0.0) {
        return Err(PyValueError::new_err(format!(
            "quantum must be finite and > 0, got {quantum}"
        )));
    }
    let faces = h_nominal.len()?;
    let series = samples
        .iter()
        .map(|x| x.as_slice())
        .collect::<Result<Vec<&[f64]>, _>>()?;
    let gather = non_negative(gather.as_slice()?, "step gather")?;
    let step_off = non_negative(step_off.as_slice()?, "step offsets")?;
    let (h0, dt) = (h_nominal.as_slice()?, piece_dt.as_slice()?);
    let steps = gather.len();
    // the outputs in numpy's buffers (large ones on huge pages): a fresh Rust vector of a
    // span's steps costs more in page faults than the pass itself
    let h = PyArray2::<f64>::zeros(py, [steps, faces], false);
    let index = PyArray1::<i64>::zeros(py, steps, false);
    let (dh, system_dt) = {
        let (mut h_rw, mut index_rw) = (h.readwrite(), index.readwrite());
        let h_s = AssertUnwindSafe(h_rw.as_slice_mut()?);
        let index_s = AssertUnwindSafe(index_rw.as_slice_mut()?);
        call_detached(py, move || {
            let (AssertUnwindSafe(h_s), AssertUnwindSafe(index_s)) = (h_s, index_s);
            chain_step_convection_into(&series, faces, &gather, &step_off, quantum, h_s)?;
            step_systems_into(h_s, h0, dt, &step_off, index_s)
        })?
    };
    let systems = system_dt.len();
    Ok((
        h,
        dh.into_pyarray(py).reshape([systems, faces])?,
        system_dt.into_pyarray(py),
        index,
    ))
}

/// Add the reduced model's functions to the module.
pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(rom_simulate_batch, m)?)?;
    m.add_function(wrap_pyfunction!(rom_simulate_switched, m)?)?;
    m.add_function(wrap_pyfunction!(rom_exact_propagator, m)?)?;
    m.add_function(wrap_pyfunction!(rom_simulate_chain, m)?)?;
    m.add_function(wrap_pyfunction!(rom_chain_systems, m)?)?;
    m.add_function(wrap_pyfunction!(rom_chain_convection, m)?)?;
    Ok(())
}
