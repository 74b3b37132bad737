"""The reduced model's construction, apart from the model itself: the shifts of the rational
Krylov space (:func:`shift_sequence`), its M-orthonormal basis (:func:`m_orthonormalise`),
the friction-face nodes whose maximum stands for the face's (:func:`face_max_cover`) and the
loading of the a-posteriori check (:func:`training_loading`). The derivation:
:mod:`fleetbrake.model.rom`."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "TRAINING_INITIAL_C",
    "face_max_cover",
    "m_orthonormalise",
    "shift_sequence",
    "training_loading",
]


TRAINING_INITIAL_C = 23.0
"""Uniform start of the training run (manoeuvre A's block temperature)."""


def training_loading(n_steps: int = 900) -> dict[str, NDArray[np.float64]]:
    """A braking (paper A's flux), a pause, a drag application and cooling, with the ambient
    changing: the loading the a-posteriori check runs."""
    t = np.arange(n_steps, dtype=np.float64)
    flux = np.where(t < 47, 44_526.0, 0.0)
    flux = np.where((t >= 200) & (t < 230), 60_000.0 * (1.0 - (t - 200) / 40.0), flux)
    flux = np.where((t >= 400) & (t < 600), 6_000.0, flux)
    ambient = 10.0 + 3.0 * np.sin(t / 150.0)
    return {"flux_w_m2": flux, "ambient_c": ambient}


def m_orthonormalise(
    core: object, x: NDArray[np.float64], tol: float = 1e-9
) -> NDArray[np.float64]:
    """M-orthonormal basis of the columns of ``x`` (two passes of block Gram-Schmidt with
    deflation of columns that add nothing new)."""
    apply = core.apply  # type: ignore[attr-defined]
    basis: list[NDArray[np.float64]] = []
    mb: list[NDArray[np.float64]] = []
    for j in range(x.shape[1]):
        v = x[:, j].copy()
        norm0 = float(np.sqrt(v @ apply(1.0, 0.0, {}, v[:, None])[:, 0]))
        if norm0 == 0.0:
            continue
        for _ in range(2):
            if basis:
                b = np.column_stack(basis)
                mbm = np.column_stack(mb)
                v -= b @ (mbm.T @ v)
        mv = apply(1.0, 0.0, {}, v[:, None])[:, 0]
        norm = float(np.sqrt(max(v @ mv, 0.0)))
        if norm <= tol * norm0:
            continue
        basis.append(v / norm)
        mb.append(mv / norm)
    return np.column_stack(basis)


def face_max_cover(face_fields: NDArray[np.float64], tol_k: float) -> NDArray[np.int64]:
    """Fewest friction-face nodes (greedy) whose maximum stays within ``tol_k`` of the whole
    face's maximum at every time of the training run."""
    true_max = face_fields.max(axis=1)
    best = np.full(true_max.shape, -np.inf)
    chosen: list[int] = []
    while True:
        shortfall = true_max - best
        if shortfall.max() <= tol_k:
            break
        # the node that most reduces the worst remaining shortfall
        gain = true_max[:, None] - np.maximum(best[:, None], face_fields)
        j = int(np.argmin(gain.max(axis=0)))
        if j in chosen:
            break
        chosen.append(j)
        best = np.maximum(best, face_fields[:, j])
    return np.array(sorted(chosen), dtype=np.int64)


def shift_sequence(count: int) -> list[float]:
    """0, then log10 s over [-4, 1] by bisection: 10, 1e-4, ~0.03, ~0.003, ~0.6, ..."""
    points = [0.0, 1.0, -4.0]
    intervals = [(-4.0, 1.0)]
    while len(points) < count:
        a, b = intervals.pop(0)
        m = 0.5 * (a + b)
        points.append(m)
        intervals += [(a, m), (m, b)]
    return [0.0] + [10.0**p for p in points[1:count]]
