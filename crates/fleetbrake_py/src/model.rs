//! The finite-element model: `ThermalModel` (see `fleetbrake.model.thermal.BlockModel`).

use std::collections::HashMap;

use numpy::{IntoPyArray, PyArray1, PyArray2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use thermal_core::mesh::{box_mesh, BlockGeometry, BlockMeshSpec};
use thermal_core::{
    CholeskyKind, Convection, ElementKind, Initial, Loading, Material, Precision, Scheme,
    ThermalModel,
};

use crate::convert::{column_major, from_column_major, points, series};
use crate::errors::{call, call_detached, InvalidParameterError, LengthMismatchError};

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

fn parse_precision(name: &str) -> PyResult<Precision> {
    Precision::from_name(name).ok_or_else(|| {
        InvalidParameterError::new_err(format!("unknown precision {name:?}; use mixed or double"))
    })
}

/// (k, rho, c) as the core's material.
fn material(values: [f64; 3]) -> Material {
    Material {
        conductivity_w_mk: values[0],
        density_kg_m3: values[1],
        specific_heat_j_kgk: values[2],
    }
}

/// Node indices and interpolation weights of probes, (P, nodes per element) each.
type ProbeWeights<'py> = (Bound<'py, PyArray2<i64>>, Bound<'py, PyArray2<f64>>);

/// The assembled finite-element model of one mesh (see `fleetbrake.model.thermal.BlockModel`).
#[pyclass(name = "ThermalModel", module = "fleetbrake._ext", frozen)]
struct PyThermalModel {
    inner: ThermalModel,
}

impl PyThermalModel {
    /// h per face operator from a name -> value map (unnamed faces: 0).
    fn face_vector(&self, h_by_face: &HashMap<String, f64>) -> PyResult<Vec<f64>> {
        let ops = &self.inner.ops;
        let mut h = vec![0.0; ops.faces.len()];
        for (name, value) in h_by_face {
            h[call(|| ops.face_index(name))?] = *value;
        }
        Ok(h)
    }
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
        let material = self::material(material);
        let spec = BlockMeshSpec {
            kind,
            refinement,
            focus_m,
            grading_ratio,
        };
        let inner = call_detached(py, || ThermalModel::block(&geometry, &spec, material, chol))?;
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
        let material = self::material(material);
        let inner = call_detached(py, || {
            ThermalModel::new(box_mesh(lengths_m, cells, kind)?, material, chol, flux_face)
        })?;
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
            let conn = call(|| mesh.face_connectivity(&name))?;
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
        let h = self.face_vector(&h_by_face)?;
        let (mut data, n, k) = column_major(&rhs);
        let data = call_detached(py, move || {
            model.solve_shifted(shift, &h, &mut data).map(|_| data)
        })?;
        from_column_major(py, data, n, k)
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
        let h = self.face_vector(&h_by_face)?;
        let (data, n, k) = column_major(&x);
        let data = call_detached(py, move || model.apply(a_m, a_k, &h, &data))?;
        from_column_major(py, data, n, k)
    }

    /// Interpolation weights of probe points: (node indices (P, npe), weights (P, npe)).
    fn probe_weights<'py>(
        &self,
        py: Python<'py>,
        probes_m: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<ProbeWeights<'py>> {
        let points = points(&probes_m, "probes_m")?;
        let model = &self.inner;
        let probes = call_detached(py, || model.probes(&points))?;
        let per = model.mesh.kind.n_nodes();
        let nodes: Vec<i64> = probes.nodes.iter().map(|&i| i as i64).collect();
        Ok((
            nodes.into_pyarray(py).reshape([points.len(), per])?,
            probes
                .weights
                .into_pyarray(py)
                .reshape([points.len(), per])?,
        ))
    }

    /// Run one loading. Series of length 1 are constants; `initial_c` of length 1 is uniform.
    /// Returns a dict of arrays (see `fleetbrake.model.thermal.SimulationResult`).
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
        let precision = parse_precision(precision)?;
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
            .map(|name| call(|| model.ops.face_index(name)))
            .collect::<PyResult<_>>()?;
        let points = points(&probes_m, "probes_m")?;
        let out = call_detached(py, || {
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
        })?;
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

/// Add the finite-element model's class to the module.
pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyThermalModel>()
}
