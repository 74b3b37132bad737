"""The faults of log files made on purpose (fleetbrake.synth.corrupt): pure, seeded, and
doing what they say."""

from __future__ import annotations

import gzip
import zlib

import numpy as np
import polars as pl
import pytest

from fleetbrake.fleet import logfile as lf
from fleetbrake.synth import corrupt
from fleetgen import simple_session


@pytest.fixture
def session() -> pl.DataFrame:
    return simple_session(rows=1000, seed=1)


def _rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def test_injectors_are_pure_and_seeded(session: pl.DataFrame) -> None:
    before = session.clone()
    runs = [
        lambda r: corrupt.drop_rows(session, r, 0.1),
        lambda r: corrupt.drop_gap(session, r, 60),
        lambda r: corrupt.duplicate_rows(session, r, 0.05),
        lambda r: corrupt.swap_neighbours(session, r, 0.05),
        lambda r: corrupt.blank_cells(session, r, 0.05),
        lambda r: corrupt.garble_cells(session, r, 0.05, ("speed_kmh",)),
        lambda r: corrupt.freeze_speed(session, r, 100),
        lambda r: corrupt.jump_speed(session, r, 5),
        lambda r: corrupt.pt1000_open_circuit(session, r, 50),
        lambda r: corrupt.pt1000_frozen(session, r, 50),
        lambda r: corrupt.pt1000_drift_to_ambient(session, r),
    ]
    for run in runs:
        assert run(_rng(5)).equals(run(_rng(5)))
        assert not run(_rng(5)).equals(session)
    assert session.equals(before)


def test_drop_rows_and_gap(session: pl.DataFrame) -> None:
    dropped = corrupt.drop_rows(session, _rng(), 0.1)
    assert dropped.height == session.height - round(0.1 * (session.height - 1))
    assert dropped["time_utc"][0] == session["time_utc"][0]
    assert dropped["time_utc"].is_in(session["time_utc"].implode()).all()
    gap = corrupt.drop_gap(session, _rng(), 90, start=200)
    assert gap.height == session.height - 90
    step_s = gap["time_utc"].diff().dt.total_seconds().drop_nulls()
    assert step_s.max() == 91
    assert step_s.arg_max() == 199


def test_duplicate_rows(session: pl.DataFrame) -> None:
    doubled = corrupt.duplicate_rows(session, _rng(), 0.05)
    assert doubled.height == session.height + 50
    assert doubled.unique(maintain_order=True).equals(session)
    assert doubled["time_utc"].is_duplicated().sum() == 100


def test_swap_neighbours(session: pl.DataFrame) -> None:
    swapped = corrupt.swap_neighbours(session, _rng(), 0.05)
    assert swapped.sort("time_utc").equals(session)
    backwards = int((swapped["time_utc"].diff().dt.total_seconds() < 0).sum())
    assert 30 <= backwards <= 50  # swaps never overlap
    assert swapped["time_utc"][0] == session["time_utc"][0]


def test_blank_and_garble_cells(session: pl.DataFrame) -> None:
    blank = corrupt.blank_cells(session, _rng(), 0.02)
    assert all(blank[c].null_count() == 20 for c in session.columns)
    only = corrupt.blank_cells(session, _rng(), 0.02, columns=("brake_pressure_bar",))
    assert only.null_count().row(0, named=True) == {
        c: (20 if c == "brake_pressure_bar" else 0) for c in session.columns
    }
    garbled = corrupt.garble_cells(session, _rng(), 0.01, ("speed_kmh", "time_utc"), text="n/a")
    assert (garbled["speed_kmh"] == "n/a").sum() == 10
    assert (garbled["time_utc"] == "n/a").sum() == 10
    assert garbled["time_utc"][0] in ("2024-03-01T06:00:00Z", "n/a")


def test_gps_speed_freeze_and_jump(session: pl.DataFrame) -> None:
    frozen = corrupt.freeze_speed(session, _rng(), 120, start=100)
    assert frozen["speed_kmh"].slice(100, 120).n_unique() == 1
    assert frozen["speed_kmh"].slice(220).equals(session["speed_kmh"].slice(220))
    jumped = corrupt.jump_speed(session, _rng(), 4, jump_kmh=50.0, max_length_s=3)
    changed = (jumped["speed_kmh"] - session["speed_kmh"]).abs()
    assert 1 <= int((changed > 0).sum()) <= 12
    assert changed.max() == pytest.approx(50.0)
    assert jumped["speed_kmh"].min() >= 0


def test_pt1000_faults(session: pl.DataFrame) -> None:
    low, high = lf.BLOCK_TEMP_VALID_C
    broken = corrupt.pt1000_open_circuit(session, _rng(), 30, start=10)
    reading = broken["block_temp_c"].slice(10, 30)
    assert reading.n_unique() == 1
    assert not low <= reading[0] <= high
    assert broken["block_temp_c"].slice(40).equals(session["block_temp_c"].slice(40))
    frozen = corrupt.pt1000_frozen(session, _rng(), 200, start=300)
    assert frozen["block_temp_c"].slice(300, 200).n_unique() == 1
    drift = corrupt.pt1000_drift_to_ambient(session, _rng(), tau_s=60.0, ambient_c=-5.0, start=500)
    assert drift["block_temp_c"].slice(0, 501).equals(session["block_temp_c"].slice(0, 501))
    tail = drift["block_temp_c"].slice(900).to_numpy()
    assert np.all(np.abs(tail + 5.0) < 0.01 * np.abs(session["block_temp_c"][900] + 5.0) + 0.1)


def test_truncate_mid_row() -> None:
    data = lf.to_csv_bytes(simple_session(rows=200))
    for seed in range(20):
        cut = corrupt.truncate_mid_row(data, _rng(seed))
        assert data.startswith(cut)
        assert not cut.endswith(b"\n")
        assert 0 <= lf.complete_rows(cut) < 200
        partial = cut.rsplit(b"\n", 1)[1]
        full_line = data[len(cut) - len(partial) :].split(b"\n", 1)[0]
        assert 0 < len(partial) < len(full_line)


def test_truncate_gzip_and_garbage() -> None:
    gz = lf.gzip_bytes(lf.to_csv_bytes(simple_session(rows=2000)))
    cut = corrupt.truncate_gzip(gz, _rng())
    assert gz.startswith(cut) and len(cut) < len(gz)
    with pytest.raises(EOFError):
        gzip.decompress(cut)
    inflater = zlib.decompressobj(wbits=31)
    inflater.decompress(cut)
    assert not inflater.eof
    binary = corrupt.garbage_bytes(_rng(), 1000)
    assert len(binary) == 1000 and binary != corrupt.garbage_bytes(_rng(1), 1000)
    text = corrupt.garbage_bytes(_rng(), 500, kind="text")
    assert len(text) <= 500 and b"time_utc" not in text
    assert corrupt.garbage_bytes(_rng(), 64, kind="zeros") == bytes(64)
    with pytest.raises(ValueError, match="kind"):
        corrupt.garbage_bytes(_rng(), 10, kind="nope")
