"""Type stubs of the Rust extension (crates/fleetbrake_py: errors.rs, convert.rs, model.rs, rom.rs, estimator.rs).

Private to fleetbrake.model: use fleetbrake.model.thermal and fleetbrake.model.rom instead.
"""

from typing import Any

import numpy as np
from numpy.typing import NDArray

__version__: str

class ThermalCoreError(ValueError): ...
class InvalidParameterError(ThermalCoreError): ...
class InvalidTimeStepError(ThermalCoreError): ...
class LengthMismatchError(ThermalCoreError): ...
class ProbeOutsideError(ThermalCoreError): ...
class UnknownFaceSetError(ThermalCoreError): ...
class NotPositiveDefiniteError(ThermalCoreError): ...
class MeshError(ThermalCoreError): ...
class LinearAlgebraError(ThermalCoreError): ...
class InternalError(ThermalCoreError): ...

class ThermalModel:
    @staticmethod
    def block(
        geometry: tuple[float, float, float, float, float, float, float],
        material: tuple[float, float, float],
        element: str,
        refinement: float,
        focus_m: tuple[float, ...] | None,
        grading_ratio: float,
        cholesky: str,
    ) -> ThermalModel: ...
    @staticmethod
    def box_(
        lengths_m: tuple[float, float, float],
        cells: tuple[int, int, int],
        material: tuple[float, float, float],
        element: str,
        flux_face: str,
        cholesky: str,
    ) -> ThermalModel: ...
    @property
    def n_nodes(self) -> int: ...
    @property
    def element(self) -> str: ...
    @property
    def factor_nnz(self) -> int: ...
    @property
    def matrix_nnz(self) -> int: ...
    @property
    def is_supernodal(self) -> bool: ...
    @property
    def ordering(self) -> str: ...
    @property
    def volume_m3(self) -> float: ...
    @property
    def cached_factorizations(self) -> int: ...
    def nodes(self) -> NDArray[np.float64]: ...
    def elements(self) -> NDArray[np.int64]: ...
    def face_sets(self) -> dict[str, NDArray[np.int64]]: ...
    def face_areas(self) -> dict[str, float]: ...
    def operators(self) -> dict[str, NDArray[Any]]: ...
    def simulate(
        self,
        dt_s: float,
        n_steps: int,
        flux_w_m2: NDArray[np.float64],
        ambient_c: NDArray[np.float64],
        h_faces: list[str],
        h_values: list[NDArray[np.float64]],
        initial_c: NDArray[np.float64],
        probes_m: NDArray[np.float64],
        theta: float,
        damped_steps: int,
        jump_fraction: float,
        precision: str,
        field_every: int,
    ) -> dict[str, Any]: ...
    def solve_shifted(
        self, shift: float, h_by_face: dict[str, float], rhs: NDArray[np.float64]
    ) -> NDArray[np.float64]: ...
    def apply(
        self, a_m: float, a_k: float, h_by_face: dict[str, float], x: NDArray[np.float64]
    ) -> NDArray[np.float64]: ...
    def probe_weights(
        self, probes_m: NDArray[np.float64]
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]: ...

def rom_simulate_switched(
    e: NDArray[np.float64],
    g: NDArray[np.float64],
    q: NDArray[np.float64],
    rotated: list[bool],
    index: NDArray[np.int64],
    repeats: NDArray[np.int64],
    u: NDArray[np.float64],
    xi0: NDArray[np.float64],
    c: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...
def rom_simulate_chain(
    e: NDArray[np.float64],
    g: NDArray[np.float64],
    q: NDArray[np.float64],
    rotated: list[bool],
    b_flux: NDArray[np.float64],
    b_faces: NDArray[np.float64],
    c_out: NDArray[np.float64],
    n_probes: int,
    step_flux: NDArray[np.float64],
    step_ambient: NDArray[np.float64],
    step_h: NDArray[np.float64],
    step_prop: NDArray[np.int64],
    piece_a: NDArray[np.int64],
    piece_b: NDArray[np.int64],
    piece_dt: NDArray[np.float64],
    step_off: NDArray[np.int64],
    at: NDArray[np.float64],
    at_off: NDArray[np.int64],
    seg_cont: NDArray[np.int64],
    seg_window: NDArray[np.int64],
    trusted: NDArray[np.float64],
    ambient: NDArray[np.float64],
    anchor_s: int,
    anchor_min_readings: int,
    window_s: int,
    tolerance_k: float,
    lag_tau_s: float | None,
    windows: NDArray[np.bool_] | None = None,
) -> tuple[list[NDArray[np.float64]], NDArray[np.uint8]]: ...
def rom_chain_convection(
    samples: list[NDArray[np.float64]],
    gather: NDArray[np.int64],
    step_off: NDArray[np.int64],
    piece_dt: NDArray[np.float64],
    h_nominal: NDArray[np.float64],
    quantum: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]: ...
def rom_chain_systems(
    h: NDArray[np.float64],
    h_nominal: NDArray[np.float64],
    piece_dt: NDArray[np.float64],
    step_off: NDArray[np.int64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]: ...
def rom_exact_propagator(
    lam: NDArray[np.float64], dt_s: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...
def rom_simulate_batch(
    lam: NDArray[np.float64],
    b_q: NDArray[np.float64],
    b_a: NDArray[np.float64],
    c_out: NDArray[np.float64],
    n_probes: int,
    dt_s: float,
    flux: NDArray[np.float64],
    drive: NDArray[np.float64],
    t_ref: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]: ...

# ``problems``: the dicts of ``fleetbrake.model.estimator.kernel._as_kernel_args``; the optional keys
# ("applied", "q_modes", "power_noise", "brake_phi"/"brake_q": the braking's power P_b per
# transition) absent or None when the option is off. ``manoeuvre_tolerances``: the filter's
# and the smoother's steady tolerances for the steps in the manoeuvre mode (None: the two
# tolerances before it there too).
def estimator_run(
    problems: list[dict[str, Any]],
    measurement_k: float,
    power_w_per_sqrt_s: float,
    smooth: bool,
    steady_tolerance: float,
    smoother_tolerance: float,
    checkpoint_steps: int,
    outputs_wanted: bool,
    switching: tuple[float, float, float, float, float, int, float] | None = None,
    manoeuvre_tolerances: tuple[float, float] | None = None,
) -> list[dict[str, Any]]: ...
