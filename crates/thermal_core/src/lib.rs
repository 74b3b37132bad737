//! Thermal core of fleetbrake: the 3D finite-element model of a cast-iron brake block.
//!
//! Laid out by the mathematics: [`quadrature`] and [`element`] (reference hexahedra), [`mesh`]
//! (structured, graded meshes of the block and of test boxes), [`assembly`] (capacity,
//! conduction, convection and face loads on one sparsity pattern), [`solver`] (faer sparse
//! Cholesky), [`probe`] (point location and interpolation), [`transient`] (theta-method time
//! integration driven by time series) and [`model`] (all of it behind one object).

// `!(x > 0.0)` is how NaN is rejected along with the out-of-range values: keep that form.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod assembly;
pub mod element;
pub mod error;
pub mod estimator;
pub mod mesh;
pub mod model;
pub mod probe;
pub mod quadrature;
pub mod rom;
pub mod simd;
pub mod solver;
pub mod transient;
pub mod trisolve;

pub use assembly::Material;
pub use element::ElementKind;
pub use error::{Result, ThermalError};
pub use mesh::{BlockGeometry, BlockMeshSpec, Mesh};
pub use model::ThermalModel;
pub use solver::CholeskyKind;
pub use transient::{
    Convection, EnergyLedger, Initial, Loading, Outputs, Precision, Scheme, Series,
};
