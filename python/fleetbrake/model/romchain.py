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

It lives beside ``simulate_chain`` (its call of the kernel is the same but for the output rows
and the keys) only because ``model/rom.py`` is a writer source: a change there rewrites every
cached acceptance fleet (hours). When the writer's version changes next, fold it into
``simulate_chain`` (an ``outputs`` argument, the keys from ``rom_chain_systems``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from fleetbrake import _ext
from fleetbrake.model.rom import ChainPieces, ChainRule, ChainRun, ReducedModel

__all__ = ["simulate_chain_sensor"]


def simulate_chain_sensor(
    model: ReducedModel,
    pieces: ChainPieces,
    *,
    trusted_c: NDArray[np.float64],
    ambient_c: NDArray[np.float64],
    rule: ChainRule,
) -> ChainRun:
    """:meth:`~fleetbrake.model.rom.ReducedModel.simulate_chain` of ``model`` with the sensor
    (the first probe) and the face mean only: ``sensor_c``, ``contact_mean_c``,
    ``window_sensor_c`` and ``window_mean_c`` are ``simulate_chain``'s bit for bit, the
    maxima (``contact_max_c``, ``window_max_c``) NaN; the anchoring the same."""
    steps = pieces.flux_w_m2.size
    faces = len(model.face_names)
    h = np.ascontiguousarray(pieces.h_w_m2k, dtype=np.float64).reshape(steps, faces)
    piece_dt = np.ascontiguousarray(pieces.dt_s, dtype=np.float64)
    step_offsets = np.ascontiguousarray(pieces.step_offsets, dtype=np.int64)
    dh, system_dt, index = _ext.rom_chain_systems(
        h, model._h_nominal_by_face(), piece_dt, step_offsets
    )
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
    )
    sensor, mean, top, shift, reference, w_sensor, w_mean, w_top = floats
    return ChainRun(sensor, mean, top, anchor, shift, reference, w_sensor, w_mean, w_top)
