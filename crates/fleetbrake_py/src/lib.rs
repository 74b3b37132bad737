//! Thin pyo3 bindings of `thermal_core`: convert arguments, call the core with the GIL released,
//! map errors once. Defaults, docstrings and validation of user input live in Python
//! (`python/fleetbrake/thermal.py`).

use std::collections::HashMap;

use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2,
    PyReadonlyArray3,
};
use pyo3::create_exception;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use thermal_core::error::catch_panic;
use thermal_core::mesh::{box_mesh, BlockGeometry, BlockMeshSpec};
use thermal_core::rom::{exact_propagator, ModalStepper, Propagators};
use thermal_core::{
    CholeskyKind, Convection, ElementKind, Initial, Loading, Material, Precision, Scheme, Series,
    ThermalError, ThermalModel,
};

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
fn to_pyerr(err: ThermalError) -> PyErr {
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

fn parse_element(name: &str) -> PyResult<ElementKind> {
    ElementKind::from_name(name).ok_or_else(|| {
        InvalidParameterError::new_err(format!("unknown element {name:?}; use hex8 or hex20"))
    })
}

fn parse_cholesky(name: &str) -> PyResult<CholeskyKind> {
    CholeskyKind::from_name(name).ok_or_else(|| {
        InvalidParameterError::new_err(format!(
            "unknown Cholesky variant {name:?}; use auto, simplicial or supernodal"
        ))
    })
}

fn series(values: &[f64]) -> Series<'_> {
    if values.len() == 1 {
        Series::Constant(values[0])
    } else {
        Series::Steps(values)
    }
}

/// Node indices and interpolation weights of probes, (P, nodes per element) each.
type ProbeWeights<'py> = (Bound<'py, PyArray2<i64>>, Bound<'py, PyArray2<f64>>);

/// h per face operator from a name -> value map (unnamed faces: 0).
fn face_vector(model: &ThermalModel, h_by_face: &HashMap<String, f64>) -> PyResult<Vec<f64>> {
    let mut h = vec![0.0; model.ops.faces.len()];
    for (name, value) in h_by_face {
        h[model.ops.face_index(name).map_err(to_pyerr)?] = *value;
    }
    Ok(h)
}

/// A (n, k) array copied into a column-major vector.
fn column_major(a: &PyReadonlyArray2<'_, f64>) -> (Vec<f64>, usize, usize) {
    let view = a.as_array();
    let (n, k) = (view.shape()[0], view.shape()[1]);
    let mut data = Vec::with_capacity(n * k);
    for col in view.columns() {
        data.extend(col.iter().copied());
    }
    (data, n, k)
}

/// A column-major vector back into a (n, k) array.
fn from_column_major(
    py: Python<'_>,
    data: Vec<f64>,
    n: usize,
    k: usize,
) -> PyResult<Bound<'_, PyArray2<f64>>> {
    // column-major (n, k) is row-major (k, n): transpose into a fresh C-ordered array
    let t = data.into_pyarray(py).reshape([k, n])?;
    let owned = t.readonly().as_array().t().to_owned();
    Ok(numpy::PyArray2::from_owned_array(py, owned))
}

/// The assembled finite-element model of one mesh (see `fleetbrake.thermal.BlockModel`).
#[pyclass(name = "ThermalModel", module = "fleetbrake._ext", frozen)]
struct PyThermalModel {
    inner: ThermalModel,
}

#[pymethods]
impl PyThermalModel {
    /// Mesh and assemble a block: geometry as (R_w, theta_c deg, H_b, t_body, h_lug, theta_lug
    /// deg, w_lug), material as (k, rho, c).
    #[staticmethod]
    #[allow(clippy::too_many_arguments)]
    fn block(
        py: Python<'_>,
        geometry: [f64; 7],
        material: [f64; 3],
        element: &str,
        refinement: f64,
        focus_m: Option<[f64; 3]>,
        grading_ratio: f64,
        cholesky: &str,
    ) -> PyResult<Self> {
        let kind = parse_element(element)?;
        let chol = parse_cholesky(cholesky)?;
        let geometry = BlockGeometry {
            wheel_radius_m: geometry[0],
            contact_angle_deg: geometry[1],
            block_width_m: geometry[2],
            body_thickness_m: geometry[3],
            lug_height_m: geometry[4],
            lug_angle_deg: geometry[5],
            lug_width_m: geometry[6],
        };
        let material = Material {
            conductivity_w_mk: material[0],
            density_kg_m3: material[1],
            specific_heat_j_kgk: material[2],
        };
        let spec = BlockMeshSpec {
            kind,
            refinement,
            focus_m,
            grading_ratio,
        };
        let inner = py
            .detach(|| catch_panic(|| ThermalModel::block(&geometry, &spec, material, chol)))
            .map_err(to_pyerr)?;
        Ok(PyThermalModel { inner })
    }

    /// Mesh and assemble a rectangular box [0, lx] x [0, ly] x [0, lz] (faces x0 .. z1).
    #[staticmethod]
    fn box_(
        py: Python<'_>,
        lengths_m: [f64; 3],
        cells: [usize; 3],
        material: [f64; 3],
        element: &str,
        flux_face: &str,
        cholesky: &str,
    ) -> PyResult<Self> {
        let kind = parse_element(element)?;
        let chol = parse_cholesky(cholesky)?;
        let material = Material {
            conductivity_w_mk: material[0],
            density_kg_m3: material[1],
            specific_heat_j_kgk: material[2],
        };
        let inner = py
            .detach(|| {
                catch_panic(|| {
                    ThermalModel::new(box_mesh(lengths_m, cells, kind)?, material, chol, flux_face)
                })
            })
            .map_err(to_pyerr)?;
        Ok(PyThermalModel { inner })
    }

    #[getter]
    fn n_nodes(&self) -> usize {
        self.inner.n_nodes()
    }

    #[getter]
    fn element(&self) -> &'static str {
        self.inner.mesh.kind.name()
    }

    #[getter]
    fn factor_nnz(&self) -> usize {
        self.inner.analysis.factor_nnz()
    }

    #[getter]
    fn matrix_nnz(&self) -> usize {
        self.inner.ops.pattern.nnz()
    }

    #[getter]
    fn ordering(&self) -> &'static str {
        self.inner.ordering
    }

    #[getter]
    fn is_supernodal(&self) -> bool {
        self.inner.analysis.is_supernodal()
    }

    #[getter]
    fn volume_m3(&self) -> f64 {
        self.inner.ops.volume_m3
    }

    #[getter]
    fn cached_factorizations(&self) -> usize {
        self.inner.cached_factorizations()
    }

    /// Node coordinates, (N, 3).
    fn nodes<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let flat: Vec<f64> = self.inner.mesh.nodes.iter().flatten().copied().collect();
        flat.into_pyarray(py).reshape([self.inner.n_nodes(), 3])
    }

    /// Connectivity in VTK order, (E, 8) or (E, 20).
    fn elements<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<i64>>> {
        let mesh = &self.inner.mesh;
        let flat: Vec<i64> = mesh.elements.iter().map(|&i| i as i64).collect();
        flat.into_pyarray(py)
            .reshape([mesh.n_elements(), mesh.kind.n_nodes()])
    }

    /// Face sets: name -> (F, 4 or 8) node indices, VTK quad order, outward normal.
    fn face_sets<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let mesh = &self.inner.mesh;
        let dict = PyDict::new(py);
        let per_face = mesh.kind.n_face_nodes();
        for name in mesh.face_set_names() {
            let conn = mesh.face_connectivity(&name).map_err(to_pyerr)?;
            let n_faces = conn.len() / per_face;
            let flat: Vec<i64> = conn.into_iter().map(|i| i as i64).collect();
            dict.set_item(&name, flat.into_pyarray(py).reshape([n_faces, per_face])?)?;
        }
        Ok(dict)
    }

    /// Face set areas (m^2).
    fn face_areas(&self) -> HashMap<String, f64> {
        self.inner
            .ops
            .faces
            .iter()
            .map(|f| (f.name.clone(), f.area_m2))
            .collect()
    }

    /// The operators on their common pattern, as CSC arrays: col_ptr, row_idx, capacity,
    /// conduction, and per face set `mass:<name>` (pattern values) and `load:<name>` (nodal).
    fn operators<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let ops = &self.inner.ops;
        let dict = PyDict::new(py);
        let idx = |v: &[usize]| v.iter().map(|&i| i as i64).collect::<Vec<i64>>();
        dict.set_item("col_ptr", idx(&ops.pattern.col_ptr).into_pyarray(py))?;
        dict.set_item("row_idx", idx(&ops.pattern.row_idx).into_pyarray(py))?;
        dict.set_item("capacity", PyArray1::from_slice(py, &ops.capacity))?;
        dict.set_item("conduction", PyArray1::from_slice(py, &ops.conduction))?;
        for f in &ops.faces {
            dict.set_item(
                format!("mass:{}", f.name),
                PyArray1::from_slice(py, &f.mass),
            )?;
            dict.set_item(
                format!("load:{}", f.name),
                PyArray1::from_slice(py, &f.load),
            )?;
        }
        Ok(dict)
    }

    /// Solve `(shift M + K + Σ h_s H_s) X = B` for B (n, k); factor cached by (shift, h).
    fn solve_shifted<'py>(
        &self,
        py: Python<'py>,
        shift: f64,
        h_by_face: HashMap<String, f64>,
        rhs: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let model = &self.inner;
        let h = face_vector(model, &h_by_face)?;
        let (mut data, n, k) = column_major(&rhs);
        py.detach(|| catch_panic(move || model.solve_shifted(shift, &h, &mut data).map(|_| data)))
            .map_err(to_pyerr)
            .and_then(|data| from_column_major(py, data, n, k))
    }

    /// `(a_m M + a_k K + Σ h_s H_s) X` for X (n, k).
    fn apply<'py>(
        &self,
        py: Python<'py>,
        a_m: f64,
        a_k: f64,
        h_by_face: HashMap<String, f64>,
        x: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let model = &self.inner;
        let h = face_vector(model, &h_by_face)?;
        let (data, n, k) = column_major(&x);
        py.detach(|| catch_panic(move || model.apply(a_m, a_k, &h, &data)))
            .map_err(to_pyerr)
            .and_then(|data| from_column_major(py, data, n, k))
    }

    /// Interpolation weights of probe points: (node indices (P, npe), weights (P, npe)).
    fn probe_weights<'py>(
        &self,
        py: Python<'py>,
        probes_m: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<ProbeWeights<'py>> {
        let view = probes_m.as_array();
        if view.shape()[1] != 3 {
            return Err(LengthMismatchError::new_err("probes_m must be (P, 3)"));
        }
        let points: Vec<[f64; 3]> = view
            .rows()
            .into_iter()
            .map(|r| [r[0], r[1], r[2]])
            .collect();
        let probes = self.inner.probes(&points).map_err(to_pyerr)?;
        let per = self.inner.mesh.kind.n_nodes();
        let nodes: Vec<i64> = probes.nodes.iter().map(|&i| i as i64).collect();
        Ok((
            nodes.into_pyarray(py).reshape([points.len(), per])?,
            probes
                .weights
                .clone()
                .into_pyarray(py)
                .reshape([points.len(), per])?,
        ))
    }

    /// Run one loading. Series of length 1 are constants; `initial_c` of length 1 is uniform.
    /// Returns a dict of arrays (see `fleetbrake.thermal.SimulationResult`).
    #[allow(clippy::too_many_arguments)]
    fn simulate<'py>(
        &self,
        py: Python<'py>,
        dt_s: f64,
        n_steps: usize,
        flux_w_m2: PyReadonlyArray1<'py, f64>,
        ambient_c: PyReadonlyArray1<'py, f64>,
        h_faces: Vec<String>,
        h_values: Vec<PyReadonlyArray1<'py, f64>>,
        initial_c: PyReadonlyArray1<'py, f64>,
        probes_m: PyReadonlyArray2<'py, f64>,
        theta: f64,
        damped_steps: usize,
        jump_fraction: f64,
        precision: &str,
        field_every: usize,
    ) -> PyResult<Bound<'py, PyDict>> {
        let model = &self.inner;
        let precision = Precision::from_name(precision).ok_or_else(|| {
            InvalidParameterError::new_err(format!(
                "unknown precision {precision:?}; use mixed or double"
            ))
        })?;
        if h_faces.len() != h_values.len() {
            return Err(LengthMismatchError::new_err(
                "h_faces and h_values differ in length",
            ));
        }
        let flux = flux_w_m2.as_slice()?;
        let ambient = ambient_c.as_slice()?;
        let initial = initial_c.as_slice()?;
        let h_slices: Vec<&[f64]> = h_values
            .iter()
            .map(|a| a.as_slice())
            .collect::<Result<_, _>>()?;
        let faces: Vec<usize> = h_faces
            .iter()
            .map(|n| model.ops.face_index(n))
            .collect::<Result<_, _>>()
            .map_err(to_pyerr)?;
        let probes_view = probes_m.as_array();
        let shape = probes_view.shape();
        if shape[1] != 3 {
            return Err(LengthMismatchError::new_err(format!(
                "probes_m must be (P, 3), got {shape:?}"
            )));
        }
        let points: Vec<[f64; 3]> = probes_view
            .rows()
            .into_iter()
            .map(|r| [r[0], r[1], r[2]])
            .collect();
        let out = py
            .detach(|| {
                catch_panic(|| {
                    let probes = model.probes(&points)?;
                    let loading = Loading {
                        dt_s,
                        n_steps,
                        flux_w_m2: series(flux),
                        ambient_c: series(ambient),
                        convection: faces
                            .iter()
                            .zip(&h_slices)
                            .map(|(&face, v)| Convection {
                                face,
                                h_w_m2k: series(v),
                            })
                            .collect(),
                        initial: if initial.len() == 1 {
                            Initial::Uniform(initial[0])
                        } else {
                            Initial::Field(initial)
                        },
                    };
                    model.simulate(
                        &loading,
                        Scheme {
                            theta,
                            damped_steps,
                            jump_fraction,
                            precision,
                        },
                        &probes,
                        field_every,
                    )
                })
            })
            .map_err(to_pyerr)?;
        let dict = PyDict::new(py);
        let n_out = out.time_s.len();
        let n_probes = out.n_probes;
        dict.set_item("time_s", out.time_s.into_pyarray(py))?;
        dict.set_item(
            "probe_c",
            out.probe_c.into_pyarray(py).reshape([n_out, n_probes])?,
        )?;
        dict.set_item("face_mean_c", out.face_mean_c.into_pyarray(py))?;
        dict.set_item("face_max_c", out.face_max_c.into_pyarray(py))?;
        let n_fields = out.field_steps.len();
        dict.set_item(
            "fields_c",
            out.fields_c
                .into_pyarray(py)
                .reshape([n_fields, model.n_nodes()])?,
        )?;
        dict.set_item("field_steps", out.field_steps.into_pyarray(py))?;
        dict.set_item("final_c", out.final_c.into_pyarray(py))?;
        dict.set_item("energy_stored_j", out.energy.stored_j)?;
        dict.set_item("energy_flux_in_j", out.energy.flux_in_j)?;
        dict.set_item("energy_convected_out_j", out.energy.convected_out_j)?;
        dict.set_item("factorizations", out.factorizations)?;
        dict.set_item("seconds_factorization", out.seconds_factorization)?;
        dict.set_item("seconds_stepping", out.seconds_stepping)?;
        Ok(dict)
    }
}

/// Step a reduced model (modal form, nominal convection, exact in time) over many events:
/// flux (E, S), drive (T_amb - T_ref) (E, S) or (E, 1), t_ref (E). Returns (probe (E, S+1, P),
/// face mean (E, S+1), face max (E, S+1)).
#[pyfunction]
#[allow(clippy::too_many_arguments)]
#[allow(clippy::type_complexity)]
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
) -> PyResult<(
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
)> {
    let c: Vec<f64> = c_out.as_array().iter().copied().collect();
    let stepper = ModalStepper::new(
        lam.as_slice()?,
        b_q.as_slice()?,
        b_a.as_slice()?,
        c,
        n_probes,
        dt_s,
    )
    .map_err(to_pyerr)?;
    let shape = flux.as_array().shape().to_vec();
    let (n_events, n_steps) = (shape[0], shape[1]);
    // C-contiguous (the Python side makes them so): read in place, no copies
    let (flux_s, drive_s, t_ref_s) = (flux.as_slice()?, drive.as_slice()?, t_ref.as_slice()?);
    let out = py
        .detach(|| catch_panic(|| stepper.simulate_batch(flux_s, drive_s, t_ref_s, n_steps)))
        .map_err(to_pyerr)?;
    let rows = n_steps + 1;
    Ok((
        out.probe_c
            .into_pyarray(py)
            .reshape([n_events * rows, n_probes])?,
        out.face_mean_c.into_pyarray(py).reshape([n_events, rows])?,
        out.face_max_c.into_pyarray(py).reshape([n_events, rows])?,
    ))
}

/// Two vectors handed back to Python.
type VectorPair<'py> = (Bound<'py, PyArray1<f64>>, Bound<'py, PyArray1<f64>>);

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
    let (e, g) = exact_propagator(lam.as_slice()?, dt_s);
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
    let props = Propagators::new(
        order,
        e.as_slice()?.to_vec(),
        g.as_slice()?.to_vec(),
        q.as_slice()?.to_vec(),
        rotated,
    )
    .map_err(to_pyerr)?;
    let to_usize = |values: &[i64], name: &str| -> PyResult<Vec<usize>> {
        values
            .iter()
            .map(|&v| {
                usize::try_from(v)
                    .map_err(|_| PyValueError::new_err(format!("{name} must be >= 0, got {v}")))
            })
            .collect()
    };
    let index = to_usize(index.as_slice()?, "propagator index")?;
    let repeats = to_usize(repeats.as_slice()?, "repeats")?
        .into_iter()
        .map(|v| {
            u32::try_from(v).map_err(|_| PyValueError::new_err(format!("repeats too large: {v}")))
        })
        .collect::<PyResult<Vec<u32>>>()?;
    let n_out = c.as_array().shape()[0];
    let (u_s, xi_s, c_s) = (u.as_slice()?, xi0.as_slice()?, c.as_slice()?);
    let (y, xi) = py
        .detach(|| catch_panic(|| props.simulate(&index, &repeats, u_s, xi_s, c_s)))
        .map_err(to_pyerr)?;
    let steps = y.len() / n_out.max(1);
    Ok((
        y.into_pyarray(py).reshape([steps, n_out])?,
        xi.into_pyarray(py),
    ))
}

#[pymodule]
fn _ext(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add_class::<PyThermalModel>()?;
    m.add_function(wrap_pyfunction!(rom_simulate_batch, m)?)?;
    m.add_function(wrap_pyfunction!(rom_simulate_switched, m)?)?;
    m.add_function(wrap_pyfunction!(rom_exact_propagator, m)?)?;
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
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
