"""The log file format: names, plausible values, writer (fleetbrake.fleet.logfile)."""

from __future__ import annotations

import datetime as dt
import gzip
from pathlib import Path, PurePosixPath

import numpy as np
import polars as pl
import pytest

from fleetbrake.fleet import logfile as lf
from fleetbrake.ingest.reading import read_log
from fleetbrake.synth import corrupt
from fleetgen import T0_UTC, simple_session

# --------------------------------------------------------------------------------------------
# File names


@pytest.mark.parametrize(
    ("wagon_id", "gz"),
    [("SGG-0001", True), ("SGG_0001", False), ("a", True), ("X" * 64, False), ("a_b-c_9", True)],
)
def test_name_round_trip(wagon_id: str, gz: bool) -> None:
    start = dt.datetime(2024, 2, 29, 23, 59, 58)
    name = lf.log_name(wagon_id, start, gzip=gz)
    assert name == f"{wagon_id}_20240229T235958Z.csv" + (".gz" if gz else "")
    parsed = lf.parse_log_name(name)
    assert parsed == lf.LogName(wagon_id, start, gzip=gz)
    assert parsed.relpath == PurePosixPath("logs", wagon_id, name)
    assert lf.parse_log_path(f"logs/{wagon_id}/{name}") == parsed


def test_name_of_aware_time_is_utc() -> None:
    start = dt.datetime(2024, 3, 1, 8, 0, 0, tzinfo=dt.timezone(dt.timedelta(hours=2)))
    assert lf.log_name("W", start, gzip=True) == "W_20240301T060000Z.csv.gz"


@pytest.mark.parametrize(
    "name",
    [
        "SGG-0001_20240301T060000.csv",  # no Z
        "SGG-0001_20240301T060000Z.txt",
        "SGG-0001_20240301T060000Z.csv.bz2",
        "SGG-0001-20240301T060000Z.csv",  # no underscore before the time
        "SGG 0001_20240301T060000Z.csv",  # space in the id
        "X" * 65 + "_20240301T060000Z.csv",  # id too long
        "SGG-0001_20241301T060000Z.csv",  # month 13
        "SGG-0001_20240230T060000Z.csv",  # 30 February
        "SGG-0001_20240301T250000Z.csv",  # hour 25
        "_20240301T060000Z.csv",  # no id
        "SGG-0001_20240301T060000Z.csv.gz.tmp",
    ],
)
def test_bad_names_are_refused_naming_the_file(name: str) -> None:
    with pytest.raises(lf.LogNameError, match=name[:8].replace("(", r"\(")):
        lf.parse_log_name(name)


@pytest.mark.parametrize(
    ("relpath", "words"),
    [
        ("logs/SGG-0002/SGG-0001_20240301T060000Z.csv", "directory of wagon SGG-0002"),
        ("logs/SGG-0001_20240301T060000Z.csv", "logs/<wagon_id>/<file name>"),
        ("logs/SGG-0001/sub/SGG-0001_20240301T060000Z.csv", "logs/<wagon_id>/<file name>"),
        ("data/SGG-0001/SGG-0001_20240301T060000Z.csv", "logs/<wagon_id>/<file name>"),
        ("logs/SGG-0001/notes.txt", "does not follow"),
    ],
)
def test_bad_paths_are_refused_naming_the_path(relpath: str, words: str) -> None:
    with pytest.raises(lf.LogNameError) as error:
        lf.parse_log_path(relpath)
    assert str(error.value).startswith(relpath)
    assert words in str(error.value)


def test_log_name_refuses_a_bad_wagon_id() -> None:
    with pytest.raises(lf.LogNameError, match="does not match"):
        lf.log_name("SGG 1", T0_UTC, gzip=False)


# --------------------------------------------------------------------------------------------
# Writer


def test_csv_bytes_exactly_as_specified() -> None:
    frame = pl.DataFrame(
        {
            "time_utc": [dt.datetime(2024, 3, 1, 6, 0, 0), dt.datetime(2024, 3, 1, 6, 0, 1)],
            "speed_kmh": [12.5, None],
            "distance_m": [0.0, 3.5],
            "elevation_m": [None, 401.25],
            "lat_deg": [46.123456, None],
            "lon_deg": [7.5, 7.500001],
            "brake_pressure_bar": [0.007, 3.801],
            "block_temp_c": [21.0, -250.0],
        }
    )
    assert lf.to_csv_bytes(frame) == (
        b"time_utc,speed_kmh,distance_m,elevation_m,lat_deg,lon_deg,brake_pressure_bar,"
        b"block_temp_c\n"
        b"2024-03-01T06:00:00Z,12.5,0.0,,46.123456,7.5,0.007,21.0\n"
        b"2024-03-01T06:00:01Z,,3.5,401.25,,7.500001,3.801,-250.0\n"
    )


def test_write_log_gzip_by_name_deterministic_and_readable(tmp_path: Path) -> None:
    frame = simple_session(rows=300)
    a = lf.write_log(tmp_path / "a" / "W_20240301T060000Z.csv.gz", frame)
    b = lf.write_log(tmp_path / "b" / "W_20240301T060000Z.csv.gz", frame)
    plain = lf.write_log(tmp_path / "W_20240301T060000Z.csv", frame)
    assert a.read_bytes() == b.read_bytes()  # no time stamp in the gzip header
    assert gzip.decompress(a.read_bytes()) == plain.read_bytes() == lf.to_csv_bytes(frame)
    assert not list(tmp_path.rglob(".*"))  # the temporary file is gone
    forced = lf.write_log(tmp_path / "forced.csv", frame, gzip=True)
    assert forced.read_bytes()[:2] == b"\x1f\x8b"


def test_writer_and_reader_round_trip_exactly() -> None:
    frame = simple_session(rows=500, seed=3)
    parsed = read_log(lf.to_csv_bytes(frame), "x.csv", T0_UTC)
    assert parsed.repairs.text() is None
    assert parsed.frame.select(frame.columns).equals(frame)


def test_writer_keeps_column_order_and_writes_strings_as_they_are() -> None:
    frame = simple_session(rows=3).select("block_temp_c", "time_utc")
    frame = frame.with_columns(pl.col("block_temp_c").cast(pl.String).fill_null("x"))
    text = lf.to_csv_bytes(frame).decode()
    assert text.splitlines()[0] == "block_temp_c,time_utc"
    assert text.splitlines()[1].endswith(",2024-03-01T06:00:00Z")


# --------------------------------------------------------------------------------------------
# Plausible values


@pytest.fixture
def session() -> pl.DataFrame:
    return simple_session(rows=1000, seed=1)


def _rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def test_every_numeric_channel_has_a_plausible_range(session: pl.DataFrame) -> None:
    assert set(lf.PLAUSIBLE_RANGES) == set(lf.FLOAT_COLUMNS)
    assert all(low < high for low, high in lf.PLAUSIBLE_RANGES.values())
    assert lf.PLAUSIBLE_RANGES["block_temp_c"] == lf.BLOCK_TEMP_VALID_C
    # what real units write stays inside, GPS jumps and frozen speeds included: those are
    # the event detection's to deal with, not impossible values
    rough = corrupt.freeze_speed(
        corrupt.jump_speed(session, _rng(), 20, jump_kmh=120.0), _rng(1), 60
    )
    for column, (low, high) in lf.PLAUSIBLE_RANGES.items():
        assert rough[column].is_between(low, high).all(), column
