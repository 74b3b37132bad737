"""A span's chain for the close loop's fits: the sensor and the face mean only.

:meth:`fleetbrake.model.rom.ReducedModel.simulate_chain` gives everything a stored timeline
needs (the probes, the face mean and the maximum over the face nodes, 25 output rows on the
default mesh) and keys its propagators with numpy over every step (the convection change from
nominal rounded, the distinct rows sorted). A fit's evaluation reads the sensor at the event
windows and, for a state-dependent effect, the face mean: :func:`simulate_chain_sensor` runs
the same chain kernel (``_ext.rom_simulate_chain``) with those two output rows only, and has
the steps' systems found by the Rust kernel in one pass
(``_ext.rom_chain_systems``: the same ``round(h - h_nominal, 12)`` keys, in the order they
first come). The propagators are the reduced model's own
(:meth:`~fleetbrake.model.rom.ReducedModel._cached_propagator`, its cache shared), so the
sensor and the face mean are ``simulate_chain``'s bit for bit (a test); the maximum is not
computed (NaN).

An evaluation's convection per step comes from Rust too (:func:`chain_convection`,
``_ext.rom_chain_convection``): the per-sample convection of each face set on each of the span's
sources (the fine samples, the coarse grids), turned into step means, gathered into the chain's
steps, rounded to the quantum on the pieces where it varies and keyed into step systems in one
call (numpy's operations, bit for bit: a test; its outputs in numpy's buffers, whose large
pages spare the page faults a fresh vector costs). And the kernel sums its outputs only where
they are read when told which window seconds are wanted (``windows``: the fit seconds; the
anchoring's seconds and every step under a sensor lag are computed whatever it says): the state
is stepped alike, so the outputs it gives are those of the full run bit for bit, the others
NaN, and it gives no timeline but the sensor's the anchoring reads.

It is a module of its own beside ``simulate_chain`` (its call of the kernel is the same but
for the output rows and the keys) because ``model/rom.py`` is a writer source: a change there
changes the version of every cached acceptance fleet (hours to write again). With such a
change it can fold into ``simulate_chain`` (an ``outputs`` argument, the keys from
``rom_chain_systems``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from fleetbrake import _ext
from fleetbrake.model.chaintypes import ChainPieces, ChainRule, ChainRun
from fleetbrake.model.rom import ReducedModel

__all__ = ["StepSystems", "chain_convection", "simulate_chain_sensor"]

StepSystems = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]
"""A chain's distinct step systems: the convection change from nominal (K, F), the time step
(K), and each step's system (T) (``_ext.rom_chain_systems``)."""


def chain_convection(
    model: ReducedModel,
    samples: Sequence[Sequence[NDArray[np.float64]]],
    *,
    gather: NDArray[np.int64],
    step_offsets: NDArray[np.int64],
    piece_dt_s: NDArray[np.float64],
    quantum_w_m2k: float,
) -> tuple[NDArray[np.float64], StepSystems]:
    """A chain's convection per step (T, F) and its step systems, in one Rust call:
    ``samples[f][i]`` the convection of ``model``'s face set ``f`` at the samples of source
    ``i`` (each source's series as long for every face set); each source's step means
    ``0.5 (h_k + h_k+1)`` concatenated, step ``t`` of the chain taking ``gather[t]`` of them,
    a face set's steps on a piece (``step_offsets``) where they vary rounded to
    ``quantum_w_m2k`` (``np.round(h / q) * q``), then the systems
    (``round(h - h_nominal, 12)`` with the piece's ``piece_dt_s``) as
    :func:`simulate_chain_sensor` keys them. Equal to those numpy operations bit for bit."""
    faces = len(model.face_names)
    if len(samples) != faces:
        raise ValueError(f"convection given for {len(samples)} face sets, the model has {faces}")
    flat = [np.ascontiguousarray(x, dtype=np.float64) for face in samples for x in face]
    h, dh, dt, index = _ext.rom_chain_convection(
        flat,
        np.ascontiguousarray(gather, dtype=np.int64),
        np.ascontiguousarray(step_offsets, dtype=np.int64),
        np.ascontiguousarray(piece_dt_s, dtype=np.float64),
        model._h_nominal_by_face(),
        float(quantum_w_m2k),
    )
    return h, (dh, dt, index)


def simulate_chain_sensor(
    model: ReducedModel,
    pieces: ChainPieces,
    *,
    trusted_c: NDArray[np.float64],
    ambient_c: NDArray[np.float64],
    rule: ChainRule,
    systems: StepSystems | None = None,
    windows: NDArray[np.bool_] | None = None,
) -> ChainRun:
    """:meth:`~fleetbrake.model.rom.ReducedModel.simulate_chain` of ``model`` with the sensor
    (the first probe) and the face mean only: ``sensor_c``, ``contact_mean_c``,
    ``window_sensor_c`` and ``window_mean_c`` are ``simulate_chain``'s bit for bit, the
    maxima (``contact_max_c``, ``window_max_c``) NaN; the anchoring the same. ``systems``:
    the steps' systems when already found (:func:`chain_convection`; None: found here).
    ``windows``: one flag per window output (``sum(window_length)``), those read; the others
    are NaN, the anchoring unchanged (a sensor lag computes every output), and the timeline
    is the sensor's only, up to the last segment's end, NaN but where the anchoring reads it
    (``contact_mean_c`` and ``contact_max_c`` empty: a caller of the windows reads no
    timeline, and fresh n-long arrays cost more in page faults than the steps). None: every
    output, as ``simulate_chain``."""
    steps = pieces.flux_w_m2.size
    faces = len(model.face_names)
    h = np.ascontiguousarray(pieces.h_w_m2k, dtype=np.float64).reshape(steps, faces)
    piece_dt = np.ascontiguousarray(pieces.dt_s, dtype=np.float64)
    step_offsets = np.ascontiguousarray(pieces.step_offsets, dtype=np.int64)
    if systems is None:
        systems = _ext.rom_chain_systems(h, model._h_nominal_by_face(), piece_dt, step_offsets)
    dh, system_dt, index = systems
    props = [
        model._cached_propagator(row, float(dt_s), "exact")
        for row, dt_s in zip(dh, system_dt, strict=True)
    ]
    if not props:  # no steps at all: one unused propagator keeps the table well formed
        props = [model._cached_propagator(np.zeros(faces), 1.0, "exact")]
    r = model.order
    eye = np.eye(r)
    rotated = [q is not None for _, _, q in props]
    # the sensor (the first probe) and the face mean: two output rows of the model's
    rows = np.ascontiguousarray(model.c_out[[0, model.n_probes]])
    floats, anchor = _ext.rom_simulate_chain(
        np.ascontiguousarray(np.stack([e for e, _, _ in props])),
        np.ascontiguousarray(np.stack([g for _, g, _ in props])),
        np.ascontiguousarray(np.stack([eye if q is None else q for _, _, q in props])),
        rotated,
        np.ascontiguousarray(model.b_flux),
        np.ascontiguousarray(model.b_faces),
        rows,
        1,
        np.ascontiguousarray(pieces.flux_w_m2, dtype=np.float64),
        np.ascontiguousarray(pieces.ambient_c, dtype=np.float64),
        h,
        index,
        np.ascontiguousarray(pieces.a, dtype=np.int64),
        np.ascontiguousarray(pieces.b, dtype=np.int64),
        piece_dt,
        step_offsets,
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
        None if windows is None else np.ascontiguousarray(windows, dtype=np.bool_),
    )
    sensor, mean, top, shift, reference, w_sensor, w_mean, w_top = floats
    return ChainRun(sensor, mean, top, anchor, shift, reference, w_sensor, w_mean, w_top)
