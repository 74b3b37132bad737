"""The estimate stage's inputs and rows, built the fast way, give the bits of the plain
formulas: the modal response of the declared inputs in cache-sized blocks
(``model.estimator.transitions.modal_response``) against the formula on the whole series at
once, and a wagon's rows built as Arrow from the estimate's arrays
(``simulation.estimates.rows.estimate_rows``) against the same columns built as a polars
frame; the dense transitions' steps gathered from one sort against a scan per transition.
Equal means equal: ``np.array_equal`` and Arrow's ``equals``, not a tolerance.
"""

from __future__ import annotations

import datetime as dt

import numpy as np
import polars as pl
import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information
import pytest

import fleetbrake.model.estimator.transitions as transitions
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.estimator import (
    ContactEstimate,
    EstimatorConfig,
    EstimatorNoise,
    WagonSeries,
    prepare,
)
from fleetbrake.model.estimator.transitions import TransitionTable, modal_response
from fleetbrake.model.rom import ReducedModel
from fleetbrake.simulation.estimates.rows import ESTIMATE_SCHEMA, estimate_rows

WAGON = WagonConfig(wagon_id="TEST-0001")


def _whole_series_response(
    rom: ReducedModel,
    table: TransitionTable,
    index: np.ndarray,
    step_flux: np.ndarray,
    drive: np.ndarray,
    r: int,
) -> np.ndarray:
    """The formula of the modal response, on the whole series at once (the dense transitions'
    steps by a scan of the series per transition)."""
    u = step_flux[:, None] * rom.b_flux[None, :] + drive @ rom.b_faces
    if r > rom.order:
        u = np.concatenate([u, np.zeros((u.shape[0], 1))], axis=1)
    g_all = np.stack(table.g)
    w = u * g_all[index]
    for k in np.flatnonzero(~np.array(table.diagonal, dtype=bool)):
        gmat = table.gmat[k]
        assert gmat is not None
        rows = index == k
        w[rows] = u[rows] @ gmat.T
    return w


def _table(rom: ReducedModel, seat_sd_k: float, dense: bool) -> TransitionTable:
    c_probe = np.append(rom.c_out[0], 1.0) if seat_sd_k > 0 else rom.c_out[0]
    table = TransitionTable(
        rom=rom,
        c_probe=c_probe,
        lag_tau_s=0.0,
        tau_p_s=600.0,
        area_m2=WAGON.geometry.contact_area_m2,
        seat_sd_k=seat_sd_k,
    )
    nominal = np.zeros(len(rom.face_names))
    for steps, gap, held, applied in [
        (1, False, False, False),
        (1, False, True, False),
        (1, False, False, True),
        (7, True, True, False),
    ]:
        table.get(nominal, steps, 1.0, gap, held, applied)
    if dense:  # a convection other than nominal: a dense transition
        table.get(np.full(len(rom.face_names), 4.0), 1, 1.0, False, False, False)
    return table


@pytest.mark.parametrize("seat_sd_k", [0.0, 0.4])
@pytest.mark.parametrize("dense", [False, True])
@pytest.mark.parametrize("block", [7, 1024, 1 << 30])
def test_the_modal_response_in_blocks_is_the_whole_series_formula_bit_for_bit(
    default_rom: ReducedModel,
    monkeypatch: pytest.MonkeyPatch,
    seat_sd_k: float,
    dense: bool,
    block: int,
) -> None:
    rom = default_rom
    rng = np.random.default_rng(14)
    steps = 5_000  # blocks of 7: 714 whole ones and a last of 2
    table = _table(rom, seat_sd_k, dense)
    r = rom.order + int(seat_sd_k > 0)
    index = rng.integers(0, len(table.g), steps).astype(np.int64)
    step_flux = np.where(rng.random(steps) < 0.3, rng.uniform(0, 4e4, steps), 0.0)
    drive = rng.uniform(0, 60.0, (steps, len(rom.face_names))) * rng.normal(0, 8.0, (steps, 1))
    monkeypatch.setattr(transitions, "RESPONSE_BLOCK_STEPS", block)
    got = modal_response(rom, table, index, step_flux, drive, r)
    want = _whole_series_response(rom, table, index, step_flux, drive, r)
    assert got.shape == (steps, r) and np.array_equal(got, want)
    empty = modal_response(rom, table, index[:0], step_flux[:0], drive[:0], r)
    assert empty.shape == (0, r)


@pytest.mark.parametrize("seat_sd_k", [0.0, 0.4])
def test_the_modal_response_of_many_dense_transitions_is_the_formula_bit_for_bit(
    default_rom: ReducedModel, seat_sd_k: float
) -> None:
    """A speed-varying convection: dense transitions among the diagonal ones, each gathered
    once from the steps sorted by transition instead of a scan of the series per
    transition; the same bits as the formula, whichever transitions the steps use (one
    used by no step, one by a single step)."""
    rom = default_rom
    rng = np.random.default_rng(15)
    table = _table(rom, seat_sd_k, dense=False)
    faces = len(rom.face_names)
    for h in (1.0, 2.5, 4.0, 7.5, 11.0):
        table.get(np.full(faces, h), 1, 1.0, False, False, False)
    assert sum(not d for d in table.diagonal) == 5
    r = rom.order + int(seat_sd_k > 0)
    steps = 3_000
    index = rng.integers(0, len(table.g) - 2, steps).astype(np.int64)  # the last: unused
    index[1_234] = len(table.g) - 2  # used by one step only
    step_flux = np.where(rng.random(steps) < 0.3, rng.uniform(0, 4e4, steps), 0.0)
    drive = rng.uniform(0, 60.0, (steps, faces)) * rng.normal(0, 8.0, (steps, 1))
    got = modal_response(rom, table, index, step_flux, drive, r)
    want = _whole_series_response(rom, table, index, step_flux, drive, r)
    assert got.shape == (steps, r) and np.array_equal(got, want)


def test_prepare_is_the_same_whatever_the_block(
    default_rom: ReducedModel, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A day's series with brakings, stops, a gap filled and one left a standstill, the seat's
    error in the state: every array of the problem the same with blocks of 7 s and of all."""
    rng = np.random.default_rng(3)
    t = np.arange(6_000.0)
    keep = ~((t > 1_000) & (t < 1_020)) & ~((t > 3_000) & (t < 4_000))
    speed = np.clip(60 + 30 * np.sin(t / 500), 0, None) * (t % 1_500 > 200)
    series = WagonSeries.of(
        time_s=t[keep],
        p_bar=np.where((t % 900) < 60, 2.5, 0.0)[keep],
        speed_kmh=speed[keep],
        ambient_c=(8 + t / 3_000)[keep],
        reading_c=(20 + rng.normal(0, 0.1, t.size))[keep],
        wagon_id=WAGON.wagon_id,
    )
    config = EstimatorConfig(seat_error_sd_k=0.3)
    monkeypatch.setattr(transitions, "RESPONSE_BLOCK_STEPS", 7)
    small = prepare(default_rom, WAGON, series, config=config)
    monkeypatch.setattr(transitions, "RESPONSE_BLOCK_STEPS", 1 << 30)
    whole = prepare(default_rom, WAGON, series, config=config)
    assert small.w.shape == whole.w.shape and np.array_equal(small.w, whole.w)
    assert np.array_equal(small.index, whole.index) and np.array_equal(small.a, whole.a)


def _polars_rows(
    wagon_id: str, revision: str, t0: dt.datetime, est: ContactEstimate
) -> pl.DataFrame:
    """The rows built as a polars frame from the same columns (NaN filled with null)."""
    times = np.datetime64(t0, "us") + (np.rint(est.time_s).astype(np.int64) * 1_000_000).astype(
        "timedelta64[us]"
    )

    def smoothed(values: np.ndarray | None) -> np.ndarray:
        return np.full(est.time_s.size, np.nan) if values is None else values

    columns: dict[str, np.ndarray] = {
        "time_utc": times,
        "contact_mean_c": est.contact_mean_c,
        "contact_mean_lo_c": est.contact_mean_lo_c,
        "contact_mean_hi_c": est.contact_mean_hi_c,
        "contact_max_c": est.contact_max_c,
        "contact_max_hi_c": est.contact_max_hi_c,
        "smoothed_contact_mean_c": smoothed(est.smoothed_contact_mean_c),
        "smoothed_contact_mean_lo_c": smoothed(est.smoothed_contact_mean_lo_c),
        "smoothed_contact_mean_hi_c": smoothed(est.smoothed_contact_mean_hi_c),
        "unexplained_power_w": est.unexplained_power_w,
        "unexplained_power_lo_w": est.unexplained_power_lo_w,
        "unexplained_power_hi_w": est.unexplained_power_hi_w,
        "innovation_k": est.innovation_k,
        "innovation_sd_k": np.sqrt(est.innovation_var_k2),
        "smoothed_contact_max_c": smoothed(est.smoothed_contact_max_c),
        "smoothed_contact_max_hi_c": smoothed(est.smoothed_contact_max_hi_c),
        "smoothed_unexplained_power_w": smoothed(est.smoothed_unexplained_power_w),
        "smoothed_unexplained_power_lo_w": smoothed(est.smoothed_unexplained_power_lo_w),
        "smoothed_unexplained_power_hi_w": smoothed(est.smoothed_unexplained_power_hi_w),
    }
    frame = pl.DataFrame(
        {
            name: pl.Series(name, values, dtype=ESTIMATE_SCHEMA[name])
            for name, values in columns.items()
        }
    )
    floats = [name for name, kind in ESTIMATE_SCHEMA.items() if kind == pl.Float64()]
    return frame.with_columns(
        pl.lit(wagon_id, dtype=pl.String).alias("wagon_id"),
        pl.lit(revision, dtype=pl.String).alias("model_revision"),
        *(pl.col(name).fill_nan(None) for name in floats),
    ).select(list(ESTIMATE_SCHEMA))


def _estimate(n: int, smoothed: bool) -> ContactEstimate:
    rng = np.random.default_rng(n)

    def a() -> np.ndarray:
        return rng.normal(50.0, 20.0, n)

    def sd() -> np.ndarray:
        return rng.uniform(0.0, 2.0, n)

    innovation = np.where(rng.random(n) < 0.2, np.nan, rng.normal(0, 0.1, n))
    innovation[:3] = [np.nan, -0.0, 0.0][:n]
    return ContactEstimate(
        wagon_id="W-1",
        time_s=np.sort(rng.choice(np.arange(3.0 * n), n, replace=False)),
        contact_mean_c=a(),
        contact_mean_sd_k=sd(),
        contact_max_c=a(),
        contact_max_sd_k=sd(),
        unexplained_power_w=np.where(rng.random(n) < 0.5, 0.0, a()),
        unexplained_power_sd_w=sd(),
        innovation_k=innovation,
        innovation_var_k2=np.where(rng.random(n) < 0.05, np.nan, sd()),
        predicted_reading_c=a(),
        log_likelihood=0.0,
        noise=EstimatorNoise(),
        frozen_fraction=0.5,
        final_state=np.zeros(2),
        final_cov=np.eye(2),
        smoothed_contact_mean_c=a() if smoothed else None,
        smoothed_contact_mean_sd_k=sd() if smoothed else None,
        smoothed_contact_max_c=a() if smoothed else None,
        smoothed_contact_max_sd_k=sd() if smoothed else None,
        smoothed_unexplained_power_w=a() if smoothed else None,
        smoothed_unexplained_power_sd_w=sd() if smoothed else None,
    )


@pytest.mark.parametrize("smoothed", [True, False])
@pytest.mark.parametrize("n", [1, 2_500])
def test_the_arrow_rows_are_the_polars_frame_of_the_same_columns(n: int, smoothed: bool) -> None:
    t0 = dt.datetime(2026, 3, 1, 5, 59, 58)
    est = _estimate(n, smoothed)
    got = estimate_rows("SGG-0042", "declared", t0, est)
    want = _polars_rows("SGG-0042", "declared", t0, est).to_arrow()
    assert got.schema.equals(want.schema)
    assert got.equals(want)
    for name in got.column_names:  # nulls where the polars frame has them
        assert got[name].null_count == want[name].null_count
    assert got["innovation_k"].null_count >= 1


def test_no_estimate_is_an_empty_table_of_the_columns() -> None:
    empty = estimate_rows("SGG-0042", "declared", None, None)
    assert empty.num_rows == 0
    assert empty.schema.equals(pl.DataFrame(schema=ESTIMATE_SCHEMA).to_arrow().schema)
    assert isinstance(empty, pa.Table)
