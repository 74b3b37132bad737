"""The estimator's transitions: the table of the distinct steps of a wagon's series (one
exact propagator per distinct convection, length and kind of step, :class:`TransitionTable`)
and the modal response to the declared inputs of each step through them
(:func:`modal_response`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from fleetbrake import _ext
from fleetbrake.model.estimator.problem import FloatArray
from fleetbrake.model.rom import ReducedModel

__all__ = ["RESPONSE_BLOCK_STEPS", "TransitionTable", "modal_response", "modal_vector"]


@dataclass
class TransitionTable:
    """The table of distinct transitions being built (keyed by convection and length)."""

    rom: ReducedModel
    c_probe: FloatArray
    lag_tau_s: float
    tau_p_s: float
    area_m2: float
    gap_sd_k: float = 0.0
    gap_tau_s: float = 1800.0
    offset_var_per_s: float = 0.0
    seat_sd_k: float = 0.0
    seat_tau_s: float = 600.0
    keys: dict[tuple[bytes, int, bool, bool, bool, bool], int] = field(default_factory=dict)
    a: list[FloatArray] = field(default_factory=list)
    gmat: list[FloatArray | None] = field(default_factory=list)
    g: list[FloatArray] = field(default_factory=list)
    diagonal: list[bool] = field(default_factory=list)
    gamma: list[FloatArray] = field(default_factory=list)
    phi: list[float] = field(default_factory=list)
    q_unit: list[float] = field(default_factory=list)
    lag: list[tuple[float, float, FloatArray, float]] = field(default_factory=list)
    q_gap: list[float] = field(default_factory=list)
    q_modes: list[FloatArray] = field(default_factory=list)
    applied: list[bool] = field(default_factory=list)
    braking: list[bool] = field(default_factory=list)
    length_s: list[float] = field(default_factory=list)
    eigen: list[tuple[FloatArray, FloatArray] | None] = field(default_factory=list)
    """Per transition, where it is dense, ``(Q, e)`` with ``a = (Q e) Qᵀ`` as made (the
    convection's operator's ``eigh``); None where it is diagonal."""

    @property
    def seat_error(self) -> bool:
        """Whether the modal state carries the seat's model error as its last coordinate."""
        return self.seat_sd_k > 0

    def get(
        self,
        dh: FloatArray,
        steps: int,
        dt_s: float,
        gap: bool,
        held: bool,
        applied: bool,
        braking: bool = False,
    ) -> int:
        """The transition of a step of ``steps`` samples at convection ``h_nominal + dh``;
        ``gap``: an unlogged standstill; ``held``: the unexplained power neither heats nor
        diffuses over the step (the wheel stands); ``applied``: the cylinder is applied (the
        quiet mode's noise is ``ManoeuvreTest.applied_quiet_w_per_sqrt_s``); ``braking``: the
        declared inputs heat the friction face over the step (the braking's power ``P_b``
        diffuses instead of decaying)."""
        key = (np.ascontiguousarray(dh).tobytes(), steps, gap, held, applied, braking)
        found = self.keys.get(key)
        if found is not None:
            return found
        rom = self.rom
        length_s = steps * dt_s
        r = rom.order
        if np.any(dh != 0.0):
            op = np.diag(rom.lam) + np.tensordot(dh, rom.h_faces, axes=1)
            lam, q = np.linalg.eigh(0.5 * (op + op.T))
            e, g = _ext.rom_exact_propagator(np.ascontiguousarray(lam), float(length_s))
            a = (q * e) @ q.T
            gmat: FloatArray | None = (q * g) @ q.T
            eigen: tuple[FloatArray, FloatArray] | None = (q, e)
            diagonal = False
        else:
            e, g = _ext.rom_exact_propagator(np.ascontiguousarray(rom.lam), float(length_s))
            a = np.diag(e)
            gmat = None
            eigen = None
            diagonal = True
        q_modes = np.zeros(r + int(self.seat_error))
        if self.seat_error:  # the seat error's coordinate: decays, no input, its own noise
            e_b = math.exp(-length_s / self.seat_tau_s)
            a = _pad(a, e_b)
            gmat = None if gmat is None else _pad(gmat, 0.0)
            eigen = None if eigen is None else (_pad(eigen[0], 1.0), np.append(eigen[1], e_b))
            g = np.append(g, 0.0)
            q_modes[r] = self.seat_sd_k**2 * -math.expm1(-2.0 * length_s / self.seat_tau_s)
            r += 1
        if gap or held:
            gamma = np.zeros(r)
        else:
            unit = modal_vector(rom.b_flux / self.area_m2, r)  # 1 W over the face, modal load
            gamma = unit * g if gmat is None else gmat @ unit
        if held:
            phi, q_unit = 1.0, 0.0
        else:
            phi = math.exp(-length_s / self.tau_p_s)
            q_unit = 0.5 * self.tau_p_s * (1.0 - phi * phi)
        if self.lag_tau_s > 0:
            la = math.exp(-length_s / self.lag_tau_s)
            c = self.lag_tau_s / length_s * (1.0 - la) - la
            b1 = 1.0 - la - c
            lag_row = b1 * (a.T @ self.c_probe) + c * self.c_probe
            lag = (la, b1, lag_row, float(b1 * (self.c_probe @ gamma)))
        else:
            lag = (0.0, 0.0, np.zeros(r), 0.0)
        self.keys[key] = len(self.a)
        self.a.append(a)
        self.gmat.append(gmat)
        self.g.append(np.asarray(g, dtype=np.float64))
        self.diagonal.append(diagonal)
        self.gamma.append(gamma)
        self.phi.append(phi)
        self.q_unit.append(q_unit)
        self.q_gap.append(
            (self.gap_sd_k**2 * -math.expm1(-length_s / self.gap_tau_s) if gap else 0.0)
            + self.offset_var_per_s * length_s
        )
        self.lag.append(lag)
        self.q_modes.append(q_modes)
        self.applied.append(applied)
        self.braking.append(braking)
        self.length_s.append(length_s)
        self.eigen.append(eigen)
        return self.keys[key]

    def eigen_arrays(self) -> tuple[FloatArray, FloatArray] | None:
        """``EstimatorProblem.eigenvectors`` and ``eigenvalues`` of the table (None without a
        dense transition): each dense transition's ``(Q, e)``, a diagonal one's the identity
        and its diagonal."""
        if all(v is None for v in self.eigen):
            return None
        r = self.a[0].shape[0]
        q = np.stack([np.eye(r) if v is None else v[0] for v in self.eigen])
        e = np.stack(
            [np.diag(a) if v is None else v[1] for a, v in zip(self.a, self.eigen, strict=True)]
        )
        return q, e


def _pad(a: FloatArray, corner: float) -> FloatArray:
    """``a`` (r, r) with a row and a column more, ``corner`` where they meet."""
    r = a.shape[0]
    out = np.zeros((r + 1, r + 1))
    out[:r, :r] = a
    out[r, r] = corner
    return out


def modal_vector(v: FloatArray, r: int) -> FloatArray:
    """A vector over the reduced model's modes as one over ``r`` coordinates (zeros for the
    seat error's)."""
    return v if v.size == r else np.concatenate([v, np.zeros(r - v.size)])


RESPONSE_BLOCK_STEPS = 1024
"""Steps per block of :func:`modal_response` on a diagonal problem (a block's two work
arrays stay in the cache: 2 x 1024 x 38 doubles, 0.6 MB; 512-2,048 measured alike)."""


def modal_response(
    rom: ReducedModel,
    table: TransitionTable,
    index: NDArray[np.int64],
    step_flux: FloatArray,
    drive: FloatArray,
    r: int,
) -> FloatArray:
    """The modal response to the declared inputs of each step (N-1, r): the modal load
    ``u = flux b_flux + drive b_faces`` (``drive``: each face's convection times the air's
    offset from ``T_ref``; a zero for the seat error's coordinate) through the step's
    transition, ``g u`` where it is diagonal, ``G u`` where dense.

    With every transition diagonal (``run``'s declared revision) it is computed in blocks
    of :data:`RESPONSE_BLOCK_STEPS` steps, the same operations on the same numbers row by
    row (the same bits: a test compares), without the four (N-1, r) temporaries of the
    whole series (their memory traffic cost more than the arithmetic)."""
    steps = step_flux.size
    seat = r - rom.order  # 1: the seat error's coordinate (no input), else 0
    g_all = np.stack(table.g) if table.g else np.zeros((0, r))
    if steps == 0:
        return np.zeros((0, r))
    if all(table.diagonal):
        w = np.empty((steps, r))
        block = min(steps, RESPONSE_BLOCK_STEPS)
        u = np.empty((block, r))
        g = np.empty((block, r))
        if seat:
            u[:, rom.order :] = 0.0
        for a in range(0, steps, block):
            b = min(a + block, steps)
            m = b - a
            load = u[:m, : rom.order]
            np.multiply(step_flux[a:b, None], rom.b_flux[None, :], out=load)
            load += drive[a:b] @ rom.b_faces
            np.take(g_all, index[a:b], axis=0, out=g[:m])
            np.multiply(u[:m], g[:m], out=w[a:b])
        return w
    u = step_flux[:, None] * rom.b_flux[None, :] + drive @ rom.b_faces
    if seat:
        u = np.concatenate([u, np.zeros((u.shape[0], 1))], axis=1)
    w = u * g_all[index]
    dense = np.flatnonzero(~np.array(table.diagonal, dtype=bool))
    if dense.size:
        # each dense transition's steps, ascending (a stable sort of the steps by transition,
        # cut where the transition changes): the rows ``index == k`` selects, found once
        # instead of a scan of the whole series per transition (a speed-varying convection
        # has a hundred and more)
        order = np.argsort(index, kind="stable")
        bounds = np.searchsorted(index[order], np.arange(len(table.diagonal) + 1))
        for k in dense:
            gmat = table.gmat[k]
            rows = order[bounds[k] : bounds[k + 1]]
            assert gmat is not None
            w[rows] = u[rows] @ gmat.T
    return w
