"""Reduced-order model of the block: the full finite-element model's answer in microseconds.

Derivation (Galerkin projection of the full model ``M T' + K(h) T = B u``):

1. **Basis.** A rational Krylov space: for shifts ``s_k`` from 0 to 10 1/s, the responses
   ``(K0 + s_k M)^-1 F`` and ``(K0 + s_k M)^-1 M (K0 + s_k M)^-1 F`` to the input vectors
   (flux face, each convected face set) and the output vectors (probe weights), with
   ``K0 = K_cond + Σ h0_s H_s`` at the nominal convection. The uniform field is in the
   basis, so uniform states and the ambient steady state are exact. M-orthonormalised.
2. **Modes.** ``V^T K0 V = W Λ W^T`` (``V^T M V = I``): in modal coordinates ``ξ`` the
   reduced system is diagonal, ``ξ' = -Λ ξ + B̃ u``, and is integrated *exactly* for inputs
   held constant over each step (``ξ_n+1 = e^{-λ dt} ξ_n + (1 - e^{-λ dt})/λ B̃ u_n``).
3. **State.** ``T = T_ref + θ`` with ``T_ref`` the uniform initial temperature: ``θ`` starts
   at zero and the air enters as ``h (T_amb - T_ref)`` (``K_cond 1 = 0``, ``H_s 1 = G_s``).
4. **Order.** Shifts are added one at a time (0 first, then bisecting log10 s over
   [-4, 1]), each adding its vectors to the space, until the a-posteriori check passes: the
   reduced and full models, integrated with the same Crank-Nicolson scheme on a training
   loading (a braking, a drag application, cooling, a varying ambient), agree within
   ``tol_sensor_k`` at the probes and ``tol_face_k`` on the friction-face mean and maximum.
   (Truncating the modes of a larger Krylov space instead is erratic: a 48-vector space is
   exact to 1e-4 K where dropping a few of its modes leaves errors of tenths of a kelvin.)

What the closed loop changes is kept physical: a convection coefficient that differs from
nominal, or varies in time, on any face set enters as ``Σ Δh_s(t) H̃_s`` (exact exponential
per distinct value); heat input and ambient are inputs; the sensor lag is a filter on the
probe output (``fleetbrake.model.rom.first_order_lag``).

The face maximum is taken over the friction-face nodes that attained it in training, plus
their neighbours (``face_max_nodes``); the a-posteriori check covers it.

Building a model at the default mesh takes about 15 processor-seconds (most of it the full
model's training run), so a model is built once for its inputs and kept, under a key that
hashes everything it depends on (:func:`cache_key`: geometry, material, mesh options, probes,
nominal convection, :data:`ROM_VERSION`). The package ships the default block's model at the
default mesh (``fleetbrake/model/data``, written by ``python -m fleetbrake.model.romdata``,
:mod:`fleetbrake.model.romdata`), so a fresh install builds none for a fleet of default
wagons. Other models are built on demand and cached on disk: in ``$FLEETBRAKE_CACHE_DIR/rom``,
else ``~/.cache/fleetbrake/rom`` (or the ``cache_dir`` a caller passes).
``FLEETBRAKE_CACHE_DIR`` is the one environment variable the package reads. An entry is
written to a temporary file of its own in the same directory and renamed into place, so
processes building the same model at once each leave a whole file, and a reader never sees a
partial one. The mesh's fineness is an explicit parameter (``refinement``,
:data:`DEFAULT_REFINEMENT` unless given).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import secrets
from collections.abc import Mapping
from dataclasses import asdict, dataclass, is_dataclass
from importlib import resources
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import IO, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fleetbrake import _ext
from fleetbrake.fleet.block import DEFAULT_AMBIENT_C, DEFAULT_CONVECTION_W_M2K
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.chaintypes import ChainPieces, ChainRule, ChainRun
from fleetbrake.model.rombasis import (
    TRAINING_INITIAL_C,
    face_max_cover,
    m_orthonormalise,
    shift_sequence,
    training_loading,
)
from fleetbrake.model.thermal import (
    AIR_FACES,
    BlockModel,
    InvalidParameterError,
    InvalidTimeStepError,
    LengthMismatchError,
    SimulationResult,
)

__all__ = [
    "CACHE_DIR_ENV",
    "DEFAULT_REFINEMENT",
    "ROM_VERSION",
    "SHIPPED_MODELS",
    "ReducedModel",
    "RomBatch",
    "RomSimulation",
    "cache_key",
    "default_cache_dir",
    "first_order_lag",
    "shipped_name",
    "wagon_model_inputs",
]

logger = logging.getLogger(__name__)

ROM_VERSION = 3
"""Bumped whenever the construction changes, so that cached models are rebuilt."""

DEFAULT_REFINEMENT = 1.0
"""Mesh refinement of the models the pipeline builds unless told otherwise: the default
mesh (about 21,000 hex20 nodes); 0.6 builds a reduced model in a fifth of the time."""

CACHE_DIR_ENV = "FLEETBRAKE_CACHE_DIR"
"""The environment variable naming the directory of built reduced models (documented; the
only one the package reads)."""


SHIPPED_MODELS: Traversable = resources.files("fleetbrake.model.data")
"""Where the package's shipped reduced models are (:func:`shipped_name` of their keys)."""

RomScheme = Literal["exact", "crank-nicolson"]


_BLAS_LIMITED = False


def _limit_blas_threads() -> None:
    """The reduced model's matrices are tiny (tens of rows): a threaded BLAS spends far more
    on waking threads than on the work (measured: a 37x37 eigh 7.3 ms threaded, 0.85 ms on
    one thread). Limit BLAS to one thread for the process, once, when a reduced model is
    first made; processes that never use one are unaffected."""
    global _BLAS_LIMITED
    if not _BLAS_LIMITED:
        from threadpoolctl import (  # type: ignore[import-untyped]  # ships no type information
            threadpool_limits,
        )

        threadpool_limits(limits=1, user_api="blas")
        _BLAS_LIMITED = True


def default_cache_dir() -> Path:
    """``$FLEETBRAKE_CACHE_DIR``, else ``~/.cache/fleetbrake``."""
    env = os.environ.get(CACHE_DIR_ENV)
    return Path(env) if env else Path.home() / ".cache" / "fleetbrake"


def cache_key(
    model_factory: Mapping[str, object],
    probes_m: ArrayLike,
    h_nominal: Mapping[str, float] | None = None,
) -> str:
    """The key of the reduced model of ``model_factory`` (the keyword arguments of
    :class:`BlockModel`) for the probes and nominal convection (None: the declared model's):
    a hash of all of them and :data:`ROM_VERSION`."""
    probes = np.asarray(probes_m, dtype=np.float64).reshape(-1, 3)
    h0 = h_nominal if h_nominal is not None else dict.fromkeys(AIR_FACES, DEFAULT_CONVECTION_W_M2K)
    key_src = {
        "factory": {
            k: (asdict(v) if is_dataclass(v) and not isinstance(v, type) else v)
            for k, v in sorted(model_factory.items())
        },
        "probes": np.round(probes, 9).tolist(),
        "h_nominal": dict(sorted(h0.items())),
        "rom_version": ROM_VERSION,
    }
    return hashlib.sha256(json.dumps(key_src, sort_keys=True, default=str).encode()).hexdigest()


def shipped_name(key: str) -> str:
    """The file name of the shipped reduced model of ``key`` in :data:`SHIPPED_MODELS`."""
    return f"rom-{key[:32]}.npz"


def wagon_model_inputs(
    wagon: WagonConfig, refinement: float
) -> tuple[dict[str, object], list[tuple[float, float, float]]]:
    """The block model's keyword arguments and the probes of a wagon's reduced model: its
    block on the mesh of ``refinement``, graded towards the sensor seat, the one probe."""
    sensor = wagon.sensor_point_m
    factory: dict[str, object] = {
        "geometry": wagon.geometry,
        "material": wagon.block_material,
        "element": "hex20",
        "refinement": float(refinement),
        "sensor_m": sensor,
    }
    return factory, [sensor]


@dataclass(frozen=True)
class RomSimulation:
    """Outputs of a reduced simulation; series have ``n_steps + 1`` rows."""

    time_s: NDArray[np.float64]
    probe_c: NDArray[np.float64]
    face_mean_c: NDArray[np.float64]
    face_max_c: NDArray[np.float64]
    final_state: NDArray[np.float64]
    """Modal state after the last step (pass as ``initial_state`` to continue)."""


@dataclass(frozen=True)
class RomBatch:
    """Outputs of :meth:`ReducedModel.simulate_batch`: ``probe_c`` (E, S+1, P), face mean
    and maximum (E, S+1)."""

    time_s: NDArray[np.float64]
    probe_c: NDArray[np.float64]
    face_mean_c: NDArray[np.float64]
    face_max_c: NDArray[np.float64]


def first_order_lag(
    signal: NDArray[np.float64], dt_s: float, tau_s: float, initial: float | None = None
) -> NDArray[np.float64]:
    """A first-order lag ``τ y' = x - y`` of a sampled signal, exact for a signal linear
    between samples (a thermistor seated with a contact resistance lags the block)."""
    x = np.asarray(signal, dtype=np.float64)
    if tau_s <= 0:
        return x.copy()
    a = np.exp(-dt_s / tau_s)
    # exact response to a ramp between samples: y1 = a y0 + (1 - a) x1 - (x1 - x0) c
    c = tau_s / dt_s * (1.0 - a) - a
    y = np.empty_like(x)
    y[0] = x[0] if initial is None else initial
    for k in range(1, x.size):
        y[k] = a * y[k - 1] + (1.0 - a) * x[k] - (x[k] - x[k - 1]) * c
    return y


class ReducedModel:
    """A reduced model of one block model, probes and nominal convection (build with
    :meth:`build` or, cached on disk, :meth:`cached`).

    Arrays (r modes, F face sets, O outputs = probes, face mean, face-max nodes): ``lam``
    (r), ``b_flux`` (r), ``b_faces`` (F, r), ``h_faces`` (F, r, r) the face mass in modal
    coordinates, ``c_out`` (O, r).
    """

    _ARRAYS = ("lam", "b_flux", "b_faces", "h_faces", "c_out")

    def __init__(self, arrays: Mapping[str, NDArray[np.float64]], meta: Mapping[str, object]):
        _limit_blas_threads()
        for name in self._ARRAYS:
            setattr(self, name, np.asarray(arrays[name], dtype=np.float64))
        self.lam: NDArray[np.float64]
        self.b_flux: NDArray[np.float64]
        self.b_faces: NDArray[np.float64]
        self.h_faces: NDArray[np.float64]
        self.c_out: NDArray[np.float64]
        self.face_names: list[str] = list(meta["face_names"])  # type: ignore[call-overload]
        self.h_nominal: dict[str, float] = dict(meta["h_nominal"])  # type: ignore[call-overload]
        self.n_probes = int(meta["n_probes"])  # type: ignore[call-overload]
        self.meta = dict(meta)

    @property
    def order(self) -> int:
        return int(self.lam.size)

    # ------------------------------------------------------------------ construction
    @classmethod
    def build(
        cls,
        model: BlockModel,
        probes_m: ArrayLike,
        *,
        h_nominal: Mapping[str, float] | None = None,
        tol_sensor_k: float = 0.005,
        tol_face_k: float = 0.03,
        max_shifts: int = 12,
    ) -> ReducedModel:
        """Derive the reduced model of ``model`` for the given probes (see module docs)."""
        core = model._core
        probes = np.ascontiguousarray(np.asarray(probes_m, dtype=np.float64).reshape(-1, 3))
        h0 = dict(
            h_nominal
            if h_nominal is not None
            else dict.fromkeys(AIR_FACES, DEFAULT_CONVECTION_W_M2K)
        )
        ops = core.operators()
        faces = sorted(k.split(":", 1)[1] for k in ops if k.startswith("load:"))
        if "friction" not in faces:
            raise InvalidParameterError("the model has no 'friction' face set")
        unknown = set(h0) - set(faces)
        if unknown:
            raise InvalidParameterError(f"h_nominal names unknown face set(s) {sorted(unknown)}")
        if not any(v > 0 for v in h0.values()):
            raise InvalidParameterError("h_nominal needs a convection coefficient > 0 somewhere")
        n = core.n_nodes
        loads = {f: np.asarray(ops[f"load:{f}"], dtype=np.float64) for f in faces}
        nodes_idx, weights = core.probe_weights(probes)
        c_probe = np.zeros((probes.shape[0], n))
        for p in range(probes.shape[0]):
            np.add.at(c_probe[p], nodes_idx[p], weights[p])
        inputs = np.column_stack([loads[f] for f in faces] + list(c_probe))
        area = float(loads["friction"].sum())
        friction_nodes = np.flatnonzero(loads["friction"] > 0)
        # the training run of the full model: the a-posteriori check, and the face nodes
        # whose maximum stands for the whole face's
        loading = training_loading()
        full = model.simulate(
            dt_s=1.0,
            flux_w_m2=loading["flux_w_m2"],
            ambient_c=loading["ambient_c"],
            initial_c=TRAINING_INITIAL_C,
            probes_m=probes,
            field_every=1,
        )
        face_nodes = friction_nodes[
            face_max_cover(full.fields_c[:, friction_nodes], 0.1 * tol_face_k)
        ]
        meta: dict[str, object] = {
            "face_names": faces,
            "h_nominal": h0,
            "n_nodes": n,
            "n_probes": int(probes.shape[0]),
            "probes_m": probes.tolist(),
            "face_max_nodes": int(face_nodes.size),
            "rom_version": ROM_VERSION,
        }
        blocks = [np.ones((n, 1))]
        rom: ReducedModel | None = None
        for count, shift in enumerate(shift_sequence(max_shifts), start=1):
            y = core.solve_shifted(shift, h0, inputs)
            blocks += [y, core.solve_shifted(shift, h0, core.apply(1.0, 0.0, {}, y))]
            if count < 3:
                continue
            basis = m_orthonormalise(core, np.column_stack(blocks))
            k0 = basis.T @ core.apply(0.0, 1.0, h0, basis)
            lam, w = np.linalg.eigh(0.5 * (k0 + k0.T))
            phi = basis @ w  # (n, r) modes, M-orthonormal
            arrays = {
                "lam": lam,
                "b_flux": phi.T @ loads["friction"],
                "b_faces": np.stack([phi.T @ loads[f] for f in faces]),
                "h_faces": np.stack([phi.T @ core.apply(0.0, 0.0, {f: 1.0}, phi) for f in faces]),
                "c_out": np.vstack(
                    [c_probe @ phi, (loads["friction"] @ phi)[None, :] / area, phi[face_nodes]]
                ),
            }
            rom = cls(arrays, {**meta, "shifts_per_s": [float(v) for v in shift_sequence(count)]})
            errors = rom._check(full, loading)
            passed = (
                errors["max_error_sensor_k"] <= tol_sensor_k
                and errors["max_error_face_mean_k"] <= tol_face_k
                and errors["max_error_face_max_k"] <= tol_face_k
            )
            rom.meta["check"] = {
                **errors,
                "tol_sensor_k": tol_sensor_k,
                "tol_face_k": tol_face_k,
                "order": rom.order,
                "passed": bool(passed),
            }
            if passed:
                break
        assert rom is not None
        return rom

    def _check(
        self, full: SimulationResult, loading: Mapping[str, NDArray[np.float64]]
    ) -> dict[str, float]:
        """Largest differences from the full model on the training loading, both integrated
        with the same Crank-Nicolson scheme (what is left is the projection's error)."""
        red = self.simulate(
            dt_s=1.0,
            flux_w_m2=loading["flux_w_m2"],
            ambient_c=loading["ambient_c"],
            initial_c=TRAINING_INITIAL_C,
            scheme="crank-nicolson",
        )
        return {
            "max_error_sensor_k": float(np.abs(red.probe_c - full.probe_c).max()),
            "max_error_face_mean_k": float(np.abs(red.face_mean_c - full.face_mean_c).max()),
            "max_error_face_max_k": float(np.abs(red.face_max_c - full.face_max_c).max()),
        }

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | Path, *, compressed: bool = False) -> None:
        """Write the model to ``path`` atomically: to a temporary file of its own in the same
        directory (a unique name, so concurrent writers never share one), flushed, then
        renamed into place; a reader sees the old file, or a whole new one. ``compressed``:
        deflated (the shipped models)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        # pid and random token: unique among processes and threads; created exclusively ("x"),
        # with the permissions the umask gives (mkstemp's would be private to the owner)
        temporary = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(8)}.tmp")
        try:
            with open(temporary, "xb") as fh:
                (np.savez_compressed if compressed else np.savez)(
                    fh,
                    meta=np.array(json.dumps(self.meta)),
                    **{k: getattr(self, k) for k in self._ARRAYS},
                )
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(temporary, path)
        except BaseException:
            temporary.unlink(missing_ok=True)
            raise

    @classmethod
    def load(cls, path: str | Path | IO[bytes], *, key: str | None = None) -> ReducedModel:
        """The model saved at ``path``; ValueError when it is of another :data:`ROM_VERSION`
        or (``key`` given) was built for another key."""
        name = getattr(path, "name", path)
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            arrays = {k: data[k] for k in data.files if k != "meta"}
        if meta.get("rom_version") != ROM_VERSION:
            raise ValueError(f"{name}: reduced model of version {meta.get('rom_version')}")
        if key is not None and meta.get("cache_key") != key:
            raise ValueError(f"{name}: reduced model of key {meta.get('cache_key')}, not {key}")
        return cls(arrays, meta)

    @classmethod
    def build_keyed(
        cls,
        model_factory: Mapping[str, object],
        probes_m: ArrayLike,
        *,
        h_nominal: Mapping[str, float] | None = None,
    ) -> ReducedModel:
        """Build the reduced model of ``model_factory`` (the keyword arguments of
        :class:`BlockModel`) for the probes, its :func:`cache_key` in ``meta["cache_key"]``."""
        model = BlockModel(**model_factory)  # type: ignore[arg-type]
        rom = cls.build(model, probes_m, h_nominal=h_nominal)
        rom.meta["cache_key"] = cache_key(model_factory, probes_m, h_nominal)
        return rom

    @classmethod
    def shipped(cls, key: str) -> ReducedModel | None:
        """The package's shipped model of ``key``, or None (none shipped, or unreadable)."""
        entry = SHIPPED_MODELS.joinpath(shipped_name(key))
        if not entry.is_file():
            return None
        try:
            with entry.open("rb") as fh:
                return cls.load(fh, key=key)
        except (OSError, ValueError, KeyError) as error:
            logger.warning("shipped reduced model %s unusable, built instead: %s", entry, error)
            return None

    @classmethod
    def cached(
        cls,
        model_factory: Mapping[str, object],
        probes_m: ArrayLike,
        *,
        h_nominal: Mapping[str, float] | None = None,
        cache_dir: str | Path | None = None,
    ) -> ReducedModel:
        """The reduced model for a block model described by ``model_factory`` (the keyword
        arguments of :class:`BlockModel`, with ``geometry`` and ``material`` dataclasses): the
        package's shipped one when it ships one of the same :func:`cache_key`, else from the
        disk cache when one was built for the same inputs, else built and stored."""
        key = cache_key(model_factory, probes_m, h_nominal)
        shipped = cls.shipped(key)
        if shipped is not None:
            return shipped
        path = Path(cache_dir or default_cache_dir()) / "rom" / f"{key[:32]}.npz"
        if path.exists():
            try:
                return cls.load(path)
            except (OSError, ValueError, KeyError):
                path.unlink(missing_ok=True)  # a damaged or outdated entry is rebuilt
        rom = cls.build_keyed(model_factory, probes_m, h_nominal=h_nominal)
        rom.save(path)
        return rom

    @classmethod
    def for_wagon(
        cls,
        wagon: WagonConfig,
        *,
        refinement: float = DEFAULT_REFINEMENT,
        cache_dir: str | Path | None = None,
    ) -> ReducedModel:
        """The reduced model of a wagon's block with its sensor seat as the one probe, at the
        declared model's nominal convection, on the mesh of ``refinement`` (1.0: the default
        mesh, about 21,000 nodes): shipped, or cached on disk (``cache_dir``, else
        :func:`default_cache_dir`)."""
        factory, probes = wagon_model_inputs(wagon, refinement)
        return cls.cached(factory, probes, cache_dir=cache_dir)

    # ------------------------------------------------------------------ simulation
    def simulate(
        self,
        *,
        dt_s: float,
        flux_w_m2: ArrayLike,
        initial_c: float,
        ambient_c: float | ArrayLike = DEFAULT_AMBIENT_C,
        h_w_m2k: Mapping[str, float | ArrayLike] | None = None,
        scheme: RomScheme = "exact",
        initial_state: ArrayLike | None = None,
    ) -> RomSimulation:
        """The loading of :meth:`BlockModel.simulate` from a uniform ``initial_c``
        (``h_w_m2k`` None: nominal convection). ``initial_state`` continues a previous run:
        pass its ``final_state`` and the same ``initial_c`` (the reference temperature)."""
        if not (np.isfinite(dt_s) and dt_s > 0):
            raise InvalidTimeStepError(f"time step must be positive and finite, got {dt_s}")
        flux = np.asarray(flux_w_m2, dtype=np.float64).reshape(-1)
        n_steps = flux.size
        if n_steps == 0:
            raise LengthMismatchError("flux_w_m2 is empty: nothing to simulate")
        if not np.isfinite(initial_c):
            raise InvalidParameterError(f"initial_c must be finite, got {initial_c}")
        ambient = _series("ambient_c", ambient_c, n_steps)
        h = dict(self.h_nominal if h_w_m2k is None else h_w_m2k)
        unknown = set(h) - set(self.face_names)
        if unknown:
            raise InvalidParameterError(
                f"unknown face set(s) {sorted(unknown)}; the model has {self.face_names}"
            )
        h_steps = np.stack(
            [_series(f"h_w_m2k[{f!r}]", h.get(f, 0.0), n_steps) for f in self.face_names], axis=1
        )  # (S, F)
        if np.any(h_steps < 0) or not np.all(np.isfinite(h_steps)):
            raise InvalidParameterError("convection coefficients must be finite and >= 0")
        if not np.all(np.isfinite(flux)) or not np.all(np.isfinite(ambient)):
            raise InvalidParameterError("flux_w_m2 and ambient_c must be finite")
        t_ref = float(initial_c)
        xi = (
            np.zeros(self.order)
            if initial_state is None
            else np.asarray(initial_state, dtype=np.float64).copy()
        )
        if xi.shape != (self.order,):
            raise LengthMismatchError(f"initial_state must have {self.order} values")
        drive = h_steps * (ambient - t_ref)[:, None]  # (S, F): h_s (T_amb - T_ref)
        u = flux[:, None] * self.b_flux[None, :] + drive @ self.b_faces  # (S, r)
        h_nom = self._h_nominal_by_face()
        keys, inverse = unique_rows(np.round(h_steps - h_nom, 12))
        props = [self._cached_propagator(key, dt_s, scheme) for key in keys]
        repeats = np.ones(n_steps, dtype=np.int64)
        if scheme == "crank-nicolson":  # damped steps: two backward-Euler half steps
            damped = np.flatnonzero(_damped_mask(flux, ambient, h_steps))
            half = {int(k): len(props) + j for j, k in enumerate(np.unique(inverse[damped]))}
            props += [self._cached_propagator(keys[k], 0.5 * dt_s, "backward-euler") for k in half]
            inverse[damped] = [half[int(k)] for k in inverse[damped]]
            repeats[damped] = 2
        r = self.order
        rotated = [q is not None for _, _, q in props]
        q_all = np.stack([np.eye(r) if q is None else q for _, _, q in props])
        y, xi = _ext.rom_simulate_switched(
            np.stack([e for e, _, _ in props]),
            np.stack([g for _, g, _ in props]),
            np.ascontiguousarray(q_all),
            rotated,
            inverse,
            repeats,
            np.ascontiguousarray(u),
            np.ascontiguousarray(xi),
            np.ascontiguousarray(self.c_out),
        )
        y += t_ref
        p = self.n_probes
        return RomSimulation(
            time_s=np.arange(n_steps + 1, dtype=np.float64) * np.float64(dt_s),
            probe_c=y[:, :p],
            face_mean_c=y[:, p],
            face_max_c=y[:, p + 1 :].max(axis=1),
            final_state=xi,
        )

    def simulate_batch(
        self,
        *,
        dt_s: float,
        flux_w_m2: ArrayLike,
        initial_c: ArrayLike,
        ambient_c: ArrayLike = DEFAULT_AMBIENT_C,
    ) -> RomBatch:
        """Many events at once at nominal convection, exact in time (the Rust kernel, events
        in parallel): ``flux_w_m2`` (E, S); ``initial_c`` (E,) uniform starts; ``ambient_c``
        a float, (E,) or (E, S)."""
        if not (np.isfinite(dt_s) and dt_s > 0):
            raise InvalidTimeStepError(f"time step must be positive and finite, got {dt_s}")
        flux = np.ascontiguousarray(np.atleast_2d(np.asarray(flux_w_m2, dtype=np.float64)))
        n_events, n_steps = flux.shape
        t_ref = np.ascontiguousarray(
            np.broadcast_to(np.asarray(initial_c, dtype=np.float64), (n_events,))
        )
        amb = np.asarray(ambient_c, dtype=np.float64)
        try:
            if amb.ndim <= 1:  # constant over each event: one drive per event
                drive = np.broadcast_to(amb, (n_events,))[:, None] - t_ref[:, None]
            else:
                drive = np.broadcast_to(amb, (n_events, n_steps)) - t_ref[:, None]
        except ValueError:
            raise LengthMismatchError(
                f"ambient_c of shape {amb.shape} does not fit {n_events} events of {n_steps} steps"
            ) from None
        drive = np.ascontiguousarray(drive)
        for name, arr in (("flux_w_m2", flux), ("ambient_c", drive), ("initial_c", t_ref)):
            # a finite sum is the cheap proof; an overflowing one gets the full check
            if not (np.isfinite(arr.sum()) or np.all(np.isfinite(arr))):
                raise InvalidParameterError(f"{name} must be finite")
        h_nom = self._h_nominal_by_face()
        b_a = np.ascontiguousarray(h_nom @ self.b_faces)
        probe, mean, fmax = _ext.rom_simulate_batch(
            np.ascontiguousarray(self.lam),
            np.ascontiguousarray(self.b_flux),
            b_a,
            np.ascontiguousarray(self.c_out),
            self.n_probes,
            float(dt_s),
            flux,
            drive,
            t_ref,
        )
        return RomBatch(
            time_s=np.arange(n_steps + 1, dtype=np.float64) * np.float64(dt_s),
            probe_c=probe.reshape(n_events, n_steps + 1, self.n_probes),
            face_mean_c=mean,
            face_max_c=fmax,
        )

    def simulate_chain(
        self,
        pieces: ChainPieces,
        *,
        trusted_c: NDArray[np.float64],
        ambient_c: NDArray[np.float64],
        rule: ChainRule,
    ) -> ChainRun:
        """One span's whole chain in one call of the Rust kernel: every segment from the
        state the one before left, re-anchored at its start to ``trusted_c`` (n, NaN where
        no trusted reading) as :func:`fleetbrake.simulation.chains.simulate_span` does, the
        event windows continued un-anchored. Exactly what :meth:`simulate` gives piece by
        piece (the same propagators: one per distinct convection and time step)."""
        steps = pieces.flux_w_m2.size
        faces = len(self.face_names)
        h = np.ascontiguousarray(pieces.h_w_m2k, dtype=np.float64).reshape(steps, faces)
        step_dt = np.repeat(pieces.dt_s, np.diff(pieces.step_offsets))
        dh = np.round(h - self._h_nominal_by_face(), 12)
        index = np.zeros(steps, dtype=np.int64)
        props: list[
            tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64] | None]
        ] = []
        for dt_s in np.unique(pieces.dt_s):
            at = np.flatnonzero(step_dt == dt_s)
            if at.size == 0:
                continue
            if not dh[at].any():
                keys, inverse = np.zeros((1, faces)), np.zeros(at.size, dtype=np.int64)
            else:
                keys, inverse = unique_rows(dh[at])
            index[at] = len(props) + inverse
            props += [self._cached_propagator(key, float(dt_s), "exact") for key in keys]
        r = self.order
        if not props:  # no steps at all: one unused propagator keeps the table well formed
            props = [self._cached_propagator(np.zeros(faces), 1.0, "exact")]
        rotated = [q is not None for _, _, q in props]
        q_all = np.stack([np.eye(r) if q is None else q for _, _, q in props])
        floats, anchor = _ext.rom_simulate_chain(
            np.ascontiguousarray(np.stack([e for e, _, _ in props])),
            np.ascontiguousarray(np.stack([g for _, g, _ in props])),
            np.ascontiguousarray(q_all),
            rotated,
            np.ascontiguousarray(self.b_flux),
            np.ascontiguousarray(self.b_faces),
            np.ascontiguousarray(self.c_out),
            self.n_probes,
            np.ascontiguousarray(pieces.flux_w_m2, dtype=np.float64),
            np.ascontiguousarray(pieces.ambient_c, dtype=np.float64),
            h,
            index,
            np.ascontiguousarray(pieces.a, dtype=np.int64),
            np.ascontiguousarray(pieces.b, dtype=np.int64),
            np.ascontiguousarray(pieces.dt_s, dtype=np.float64),
            np.ascontiguousarray(pieces.step_offsets, dtype=np.int64),
            np.ascontiguousarray(pieces.at, dtype=np.float64),
            np.ascontiguousarray(pieces.at_offsets, dtype=np.int64),
            np.ascontiguousarray(pieces.window_continuation, dtype=np.int64),
            np.ascontiguousarray(pieces.window_length, dtype=np.int64),
            np.ascontiguousarray(trusted_c, dtype=np.float64),
            np.ascontiguousarray(ambient_c, dtype=np.float64),
            rule.anchor_s,
            rule.anchor_min_readings,
            rule.window_s,
            float(rule.tolerance_k),
            None if rule.lag_tau_s is None else float(rule.lag_tau_s),
        )
        sensor, mean, top, shift, reference, w_sensor, w_mean, w_top = floats
        return ChainRun(sensor, mean, top, anchor, shift, reference, w_sensor, w_mean, w_top)

    def _h_nominal_by_face(self) -> NDArray[np.float64]:
        """The nominal convection coefficient of each face set, in ``face_names`` order."""
        return np.array([self.h_nominal.get(f, 0.0) for f in self.face_names])

    _PROPAGATOR_CACHE_SIZE = 2048

    def _cached_propagator(
        self, dh: NDArray[np.float64], dt_s: float, scheme: str
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64] | None]:
        """:meth:`_propagator`, remembered across calls: a convection varying with speed
        comes back to the same values again and again (one eigendecomposition each)."""
        cache: dict[tuple[bytes, float, str], tuple] = self.__dict__.setdefault("_props", {})
        key = (np.ascontiguousarray(dh).tobytes(), float(dt_s), scheme)
        hit = cache.get(key)
        if hit is None:
            if len(cache) >= self._PROPAGATOR_CACHE_SIZE:
                cache.clear()
            hit = cache[key] = self._propagator(dh, dt_s, scheme)
        return hit

    def _propagator(
        self, dh: NDArray[np.float64], dt_s: float, scheme: str
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64] | None]:
        """(e, g, Q): ξ_{n+1} = Q [e ⊙ (Qᵀ ξ_n) + g ⊙ (Qᵀ u)] in the eigenbasis Q of the
        reduced operator at this convection (Q None: the nominal, already diagonal)."""
        if np.any(dh != 0.0):
            a = np.diag(self.lam) + np.tensordot(dh, self.h_faces, axes=1)
            lam, q = np.linalg.eigh(0.5 * (a + a.T))
        else:
            lam, q = self.lam, None
        x = lam * dt_s
        if scheme == "exact":
            e, g = _ext.rom_exact_propagator(np.ascontiguousarray(lam, dtype=np.float64), dt_s)
        elif scheme == "crank-nicolson":
            e = (1.0 - 0.5 * x) / (1.0 + 0.5 * x)
            g = dt_s / (1.0 + 0.5 * x)
        else:  # backward Euler
            e = 1.0 / (1.0 + x)
            g = dt_s / (1.0 + x)
        return e, g, q


def _series(name: str, value: float | ArrayLike, n_steps: int) -> NDArray[np.float64]:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.size == 1:
        return np.full(n_steps, float(arr[0]))
    if arr.size != n_steps:
        raise LengthMismatchError(f"{name} has {arr.size} values, expected {n_steps}")
    return arr


def unique_rows(
    values: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """``np.unique(values, axis=0, return_inverse=True)`` (the sorted distinct rows, and each
    row's index among them) for rows that come in runs, as a convection series does: the runs'
    first rows are compared, not every row (the sort of every row cost more than the kernel)."""
    if len(values) == 0:
        return values.reshape(0, *values.shape[1:]), np.zeros(0, dtype=np.int64)
    starts = np.flatnonzero(np.r_[True, np.any(values[1:] != values[:-1], axis=1)])
    keys, run_index = np.unique(values[starts], axis=0, return_inverse=True)
    lengths = np.diff(np.r_[starts, len(values)])
    return keys, np.repeat(run_index.reshape(-1).astype(np.int64), lengths)


def _damped_mask(
    flux: NDArray[np.float64], ambient: NDArray[np.float64], h: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """The full model's damped steps (start and jumps of > 5 % of a series' magnitude)."""
    mask = np.zeros(flux.size, dtype=bool)
    mask[0] = True
    for s in [flux, ambient, *h.T]:
        scale = np.abs(s).max()
        if scale > 0 and s.size > 1:
            jumps = np.flatnonzero(np.abs(np.diff(s)) > 0.05 * scale) + 1
            mask[jumps] = True
    return mask
