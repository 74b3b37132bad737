"""Braking event detection (fleetbrake.ingest.detection, fleetbrake.ingest.events): accuracy on generated sessions, rules, increments."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import duckdb
import numpy as np
import polars as pl
import pytest

from fleetbrake.ingest import events as events_module
from fleetbrake.ingest.config import EventConfig, IngestConfig
from fleetbrake.ingest.detection import EVENT_COLUMNS, detect_events, shrinking_running_median
from fleetbrake.ingest.files import run_ingest
from fleetbrake.synth import corrupt
from fleetgen import T0_UTC, Session, TrueEvent, make_session, write_registry, write_session

WAGON = "SGG-0001"
START_TOLERANCE_S = 3.0


def score(truth: list[TrueEvent], found: pl.DataFrame) -> tuple[float, float, float]:
    """(share of true events found with a start within 3 s, share of detected events that are
    spurious, share of found events of the right kind)."""
    starts = found["start_utc"].to_list()
    kinds = found["kind"].to_list()
    matched: set[int] = set()
    right_kind = 0
    for event in truth:
        best = None
        for i, start in enumerate(starts):
            gap_s = abs((start - event.onset_utc).total_seconds())
            if i not in matched and gap_s <= START_TOLERANCE_S:
                best = i
                break
        if best is not None:
            matched.add(best)
            right_kind += kinds[best] == event.kind
    found_share = len(matched) / len(truth)
    spurious_share = (len(starts) - len(matched)) / max(len(starts), 1)
    return found_share, spurious_share, right_kind / max(len(matched), 1)


def frame_of(
    pressure_bar: list[float] | np.ndarray,
    *,
    speed_kmh: float | np.ndarray = 72.0,
    start_utc: dt.datetime = T0_UTC,
    block_temp_c: float | np.ndarray = 30.0,
) -> pl.DataFrame:
    """A session at 1 Hz from a pressure series (speed and temperature constant unless given),
    with every column of a log file."""
    n = len(pressure_bar)
    speed = np.broadcast_to(np.asarray(speed_kmh, dtype=float), (n,))
    return pl.DataFrame(
        {
            "time_utc": pl.datetime_range(
                start_utc, start_utc + dt.timedelta(seconds=n - 1), "1s", eager=True
            ),
            "speed_kmh": speed,
            "distance_m": np.cumsum(speed / 3.6) - speed[0] / 3.6,
            "elevation_m": np.full(n, 400.0),
            "lat_deg": np.full(n, 46.0),
            "lon_deg": np.full(n, 8.0),
            "brake_pressure_bar": np.asarray(pressure_bar, dtype=float),
            "block_temp_c": np.broadcast_to(np.asarray(block_temp_c, dtype=float), (n,)),
            "ambient_temp_c": np.full(n, 10.0),
        }
    )


def pulse(before_s: int, on_s: int, after_s: int, p_bar: float = 2.0) -> list[float]:
    return [0.0] * before_s + [p_bar] * on_s + [0.0] * after_s


# --------------------------------------------------------------------------------------------
# Accuracy on generated sessions


def test_generated_sessions_clean() -> None:
    truth: list[TrueEvent] = []
    found = []
    for seed in range(12):
        session = make_session(np.random.default_rng(seed), T0_UTC + dt.timedelta(days=seed))
        truth += session.events
        found.append(detect_events(session.frame, WAGON))
    events = pl.concat(found)
    assert len(truth) >= 140
    assert {e.kind for e in truth} == {"stop", "slowdown", "drag"}
    found_share, spurious, right_kind = score(truth, events)
    assert found_share >= 0.98
    assert spurious <= 0.02
    assert right_kind >= 0.95
    assert events["complete"].all()
    assert (events["p_mean_bar"] > 0.2).all() and (events["p_mean_bar"] < 3.8).all()


def test_low_pressure_brakings_are_found() -> None:
    truth: list[TrueEvent] = []
    found = []
    for seed in range(6):
        session = make_session(
            np.random.default_rng(100 + seed),
            T0_UTC + dt.timedelta(days=seed),
            kinds=("slowdown",),
            p_range_bar=(0.4, 0.6),
        )
        truth += session.events
        found.append(detect_events(session.frame, WAGON))
    found_share, spurious, _ = score(truth, pl.concat(found))
    assert found_share >= 0.98 and spurious <= 0.02


def _imperfect(session: Session, rng: np.random.Generator) -> pl.DataFrame:
    """Every imperfection of fleet-data.md that a readable file can have."""
    frame = session.frame
    # long gaps (30 s to 2 min) while cruising, from the end so that row numbers hold
    quiet = [q for q in session.quiet if q[1] - q[0] > 150]
    for a, _ in sorted(rng.choice(quiet, size=min(3, len(quiet)), replace=False).tolist())[::-1]:
        frame = corrupt.drop_gap(frame, rng, int(rng.integers(30, 120)), start=a + 5)
    for _ in range(8):  # short gaps anywhere
        frame = corrupt.drop_gap(frame, rng, int(rng.integers(2, 9)))
    frame = corrupt.drop_rows(frame, rng, 0.02)
    frame = corrupt.duplicate_rows(frame, rng, 0.01)
    frame = corrupt.swap_neighbours(frame, rng, 0.01)
    frame = corrupt.jump_speed(frame, rng, 10)
    frame = corrupt.freeze_speed(frame, rng, 60)
    frame = corrupt.pt1000_open_circuit(frame, rng, 120)
    frame = corrupt.pt1000_frozen(frame, rng, 200)
    frame = corrupt.blank_cells(frame, rng, 0.01)
    return corrupt.garble_cells(frame, rng, 0.002, ("brake_pressure_bar", "speed_kmh"))


def test_generated_fleet_with_every_imperfection_end_to_end(tmp_path: Path) -> None:
    fleet, db = tmp_path / "fleet", tmp_path / "fleet.duckdb"
    wagons = ["SGG-0001", "SGG-0002", "SGG-0003"]
    write_registry(fleet, wagons)
    rng = np.random.default_rng(7)
    truth: dict[str, list[TrueEvent]] = {w: [] for w in wagons}
    for w, wagon in enumerate(wagons):
        for k in range(4):
            start = T0_UTC + dt.timedelta(days=k, hours=w)
            session = make_session(rng, start, n_events=14)
            truth[wagon] += session.events
            frame = _imperfect(session, rng)
            write_session(fleet, wagon, frame, start, gzip=bool(k % 2))
    report = run_ingest(fleet, db, progress=False)
    assert not report.quarantined
    con = duckdb.connect(str(db), read_only=True)
    try:
        events = con.sql("SELECT * FROM events ORDER BY wagon_id, start_utc").pl()
        view = con.sql("SELECT * FROM v_events").pl()
    finally:
        con.close()
    assert view.height == events.height
    all_truth = [e for w in wagons for e in truth[w]]
    found_share, spurious, right_kind = score(
        [e for w in wagons for e in truth[w]],
        pl.concat([events.filter(pl.col("wagon_id") == w) for w in wagons]),
    )
    assert len(all_truth) == 168
    for w in wagons:
        per_wagon, _, _ = score(truth[w], events.filter(pl.col("wagon_id") == w))
        assert per_wagon >= 0.95, w
    assert found_share >= 0.98
    assert spurious <= 0.02
    assert right_kind >= 0.95
    assert events["event_id"].n_unique() == events.height
    assert (
        events["event_id"]
        == events["wagon_id"] + "-" + events["start_utc"].dt.strftime("%Y%m%dT%H%M%S")
    ).all()


# --------------------------------------------------------------------------------------------
# Rules


def test_attributes_of_a_known_application() -> None:
    pressure = pulse(100, 40, 100)
    temp = np.full(240, 30.0)
    temp[100] = np.nan  # no reading at the activation: the one 3 s before counts
    temp[97] = 27.5
    temp[98:100] = np.nan
    events = detect_events(frame_of(pressure, block_temp_c=temp), WAGON)
    assert events.columns == list(EVENT_COLUMNS)
    (event,) = events.iter_rows(named=True)
    assert event["event_id"] == "SGG-0001-20240301T060140"
    assert event["start_utc"] == T0_UTC + dt.timedelta(seconds=100)
    assert event["end_utc"] == T0_UTC + dt.timedelta(seconds=140)
    assert event["duration_s"] == 40.0
    assert event["p_mean_bar"] == pytest.approx((39 * 2.0 + 1.0) / 40)  # eq. 1, trapezoidal
    assert event["p_max_bar"] == 2.0
    assert event["distance_m"] == pytest.approx(800.0)
    assert event["v_start_kmh"] == event["v_end_kmh"] == pytest.approx(72.0)
    assert event["t_block_start_c"] == 27.5
    assert event["kind"] == "slowdown"
    assert event["complete"] is True


def test_block_temperature_at_activation_is_null_when_faulty() -> None:
    temp = np.full(240, 30.0)
    temp[90:120] = np.nan  # out of range readings are stored as null temperatures
    (event,) = detect_events(frame_of(pulse(100, 40, 100), block_temp_c=temp), WAGON).iter_rows(
        named=True
    )
    assert event["t_block_start_c"] is None


def test_block_temperature_of_a_broken_wire_at_activation_is_null(tmp_path: Path) -> None:
    fleet, db = tmp_path / "fleet", tmp_path / "fleet.duckdb"
    write_registry(fleet, [WAGON])
    temp = np.full(240, 30.0)
    temp[100:110] = 950.0  # open circuit from the activation on; valid 1 s before
    missing = np.full(240, 30.0)
    missing[100] = np.nan  # no reading at the activation: the one 1 s before counts
    start = T0_UTC + dt.timedelta(hours=1)
    write_session(fleet, WAGON, frame_of(pulse(100, 40, 100), block_temp_c=temp), T0_UTC)
    write_session(
        fleet, WAGON, frame_of(pulse(100, 40, 100), block_temp_c=missing, start_utc=start), start
    )
    run_ingest(fleet, db, progress=False)
    assert _events(db)["t_block_start_c"].to_list() == [None, 30.0]


def test_distance_from_speed_when_the_file_has_none() -> None:
    frame = frame_of(pulse(100, 40, 100)).with_columns(
        pl.lit(None, dtype=pl.Float64).alias("distance_m")
    )
    (event,) = detect_events(frame, WAGON).iter_rows(named=True)
    assert event["distance_m"] == pytest.approx(800.0)


def test_hysteresis_does_not_fragment_a_hovering_application() -> None:
    rng = np.random.default_rng(0)
    hover = list(0.2 + 0.15 * rng.random(90))  # between 0.2 and 0.35, crossing 0.3 often
    events = detect_events(frame_of([0.0] * 60 + [0.4] + hover + [0.0] * 60), WAGON)
    assert events.height == 1
    assert events["duration_s"][0] == 91  # from the 0.4 bar sample to the first 0.0


def test_short_spike_is_no_event() -> None:
    assert detect_events(frame_of(pulse(60, 4, 60, 0.8)), WAGON).is_empty()
    assert detect_events(frame_of(pulse(60, 12, 60, 0.8)), WAGON).height == 1


def test_applications_close_together_are_merged() -> None:
    close = pulse(60, 30, 0) + [0.0] * 10 + pulse(0, 30, 60)
    far = pulse(60, 30, 0) + [0.0] * 40 + pulse(0, 30, 60)
    assert detect_events(frame_of(close), WAGON)["duration_s"].to_list() == [70.0]
    assert detect_events(frame_of(far), WAGON)["duration_s"].to_list() == [30.0, 30.0]


def test_residual_pressure_does_not_stretch_an_event() -> None:
    pressure = [0.0] * 60 + [1.5] * 40 + [0.1] * 300
    (event,) = detect_events(frame_of(pressure), WAGON).iter_rows(named=True)
    assert event["duration_s"] == 40 + 30  # first sample below 0.15, then at most 30 s
    assert event["complete"] is True


def test_an_event_does_not_bridge_a_long_data_gap() -> None:
    frame = frame_of(pulse(60, 200, 60))
    gapped = frame.filter(
        (pl.col("time_utc") < T0_UTC + dt.timedelta(seconds=120))
        | (pl.col("time_utc") >= T0_UTC + dt.timedelta(seconds=180))
    )
    events = detect_events(gapped, WAGON)
    assert events["start_utc"].to_list() == [
        T0_UTC + dt.timedelta(seconds=60),
        T0_UTC + dt.timedelta(seconds=180),
    ]
    assert events["end_utc"][0] == T0_UTC + dt.timedelta(seconds=119)
    assert events["complete"].to_list() == [False, False]


def test_short_data_gaps_and_empty_pressure_cells() -> None:
    frame = frame_of(pulse(60, 200, 60))
    short_gap = frame.filter(
        (pl.col("time_utc") < T0_UTC + dt.timedelta(seconds=120))
        | (pl.col("time_utc") >= T0_UTC + dt.timedelta(seconds=130))
    )
    assert detect_events(short_gap, WAGON)["complete"].to_list() == [True]
    blank_20_s = frame.with_columns(
        pl.when(pl.int_range(pl.len()).is_between(120, 139))
        .then(None)
        .otherwise(pl.col("brake_pressure_bar"))
        .alias("brake_pressure_bar")
    )
    assert detect_events(blank_20_s, WAGON).height == 2  # the pressure is unknown for 20 s


def test_kinds_stop_slowdown_drag() -> None:
    n = 600
    descending = detect_events(frame_of(pulse(60, 300, 240, 0.6), speed_kmh=60.0), WAGON)
    assert descending["kind"].to_list() == ["drag"]
    to_a_stop = np.concatenate([np.full(60, 60.0), np.linspace(60, 0, 300), np.zeros(240)])
    assert detect_events(frame_of(pulse(60, 310, 230, 0.6), speed_kmh=to_a_stop), WAGON)[
        "kind"
    ].to_list() == ["stop"]
    hard = detect_events(frame_of(pulse(60, 300, 240, 2.5), speed_kmh=60.0), WAGON)
    assert hard["kind"].to_list() == ["slowdown"]
    short = detect_events(frame_of(pulse(60, 60, n - 120, 0.6), speed_kmh=60.0), WAGON)
    assert short["kind"].to_list() == ["slowdown"]


def test_gps_speed_jump_at_the_activation_is_ignored() -> None:
    speed = np.full(240, 72.0)
    speed[99:102] = 140.0
    (event,) = detect_events(frame_of(pulse(100, 40, 100), speed_kmh=speed), WAGON).iter_rows(
        named=True
    )
    assert event["v_start_kmh"] == pytest.approx(72.0)


def test_order_and_repeats_of_samples_do_not_matter() -> None:
    frame = frame_of(pulse(100, 40, 100))
    shuffled = pl.concat([frame, frame.slice(50, 100)]).sample(fraction=1.0, shuffle=True, seed=1)
    assert detect_events(shuffled, WAGON).equals(detect_events(frame, WAGON))


def test_config_is_checked() -> None:
    with pytest.raises(ValueError, match="p_off_bar"):
        EventConfig(p_on_bar=0.1, p_off_bar=0.2)
    with pytest.raises(ValueError, match="max_gap_s"):
        EventConfig(max_gap_s=-1)


# --------------------------------------------------------------------------------------------
# Incremental detection in the warehouse


def _events(db: Path) -> pl.DataFrame:
    con = duckdb.connect(str(db), read_only=True)
    try:
        return con.sql("SELECT * FROM events ORDER BY start_utc").pl()
    finally:
        con.close()


def test_an_event_across_two_files_is_recomputed_when_the_second_arrives(tmp_path: Path) -> None:
    fleet, db = tmp_path / "fleet", tmp_path / "fleet.duckdb"
    write_registry(fleet, [WAGON])
    other = frame_of(pulse(60, 40, 100), start_utc=T0_UTC - dt.timedelta(hours=5))
    write_session(fleet, WAGON, other, other["time_utc"][0])
    whole = frame_of(pulse(100, 40, 300) + pulse(0, 60, 200))
    first, second = whole.slice(0, 120), whole.slice(120)
    write_session(fleet, WAGON, first, T0_UTC)
    run_ingest(fleet, db, progress=False)
    before = _events(db)
    assert before["complete"].to_list() == [True, False]
    assert before["end_utc"][1] == T0_UTC + dt.timedelta(seconds=119)

    write_session(fleet, WAGON, second, second["time_utc"][0])
    report = run_ingest(fleet, db, progress=False)
    after = _events(db)
    assert after.drop("detected_utc").equals(
        pl.concat([before.slice(0, 1), detect_events(whole, WAGON).with_columns()], how="diagonal")
        .drop("detected_utc")
        .cast(dict(after.drop("detected_utc").schema))
    )
    assert after["complete"].to_list() == [True, True, True]
    assert after.row(0) == before.row(0)  # the other session's event is left alone
    assert report.events is not None
    assert (report.events.added, report.events.removed, report.events.unchanged) == (2, 1, 0)


def test_replaced_file_takes_its_events_along(tmp_path: Path) -> None:
    fleet, db = tmp_path / "fleet", tmp_path / "fleet.duckdb"
    write_registry(fleet, [WAGON])
    write_session(fleet, WAGON, frame_of(pulse(100, 40, 100)), T0_UTC)
    run_ingest(fleet, db, progress=False)
    assert _events(db).height == 1
    write_session(fleet, WAGON, frame_of([0.0] * 240), T0_UTC)
    report = run_ingest(fleet, db, progress=False, config=IngestConfig())
    assert _events(db).is_empty()
    assert report.events is not None and report.events.removed == 1
    con = duckdb.connect(str(db), read_only=True)
    try:
        assert con.execute("SELECT count(*) FROM event_dirty").fetchone() == (0,)
    finally:
        con.close()


def test_loading_a_few_chains_at_a_time_gives_the_same_events(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    fleet = tmp_path / "fleet"
    write_registry(fleet, [WAGON])
    rng = np.random.default_rng(3)
    for k in range(6):
        start = T0_UTC + dt.timedelta(hours=2 * k)
        write_session(fleet, WAGON, make_session(rng, start, n_events=3).frame, start)
    whole = run_ingest(fleet, tmp_path / "a.duckdb", progress=False)
    monkeypatch.setattr(events_module, "_LOAD_ROWS", 1000)  # every chain loaded alone
    alone = run_ingest(fleet, tmp_path / "b.duckdb", progress=False)
    monkeypatch.setattr(events_module, "_LOAD_ROWS", 5000)  # two or three chains together
    pairs = run_ingest(fleet, tmp_path / "c.duckdb", progress=False)
    assert whole.events is not None and whole.events.chains == 6 and whole.events.added >= 18
    expected = _events(tmp_path / "a.duckdb").drop("detected_utc")
    assert _events(tmp_path / "b.duckdb").drop("detected_utc").equals(expected)
    assert _events(tmp_path / "c.duckdb").drop("detected_utc").equals(expected)
    assert alone.events is not None and pairs.events is not None


def test_chains_and_windows() -> None:
    t = [T0_UTC + dt.timedelta(seconds=s) for s in range(0, 1000, 10)]
    files = [(t[0], t[10], 101), (t[11], t[20], 90), (t[30], t[40], 101), (t[35], t[38], 4)]
    chains = events_module._chains(files, max_gap_s=15)
    assert [(c.from_utc, c.to_utc, c.rows) for c in chains] == [
        (t[0], t[20], 191),
        (t[30], t[40], 105),
    ]
    merged = events_module._merged([(t[50], t[60]), (t[5], t[6]), (t[59], t[70])], dt.timedelta(0))
    assert merged == [(t[5], t[6]), (t[50], t[70])]
    assert events_module._overlaps(merged, t[6], t[7])
    assert not events_module._overlaps(merged, t[7], t[49])
    assert events_module._overlaps(merged, t[0], t[99])
    assert not events_module._overlaps(merged, t[71], t[99])


# --------------------------------------------------------------------------------------------
# The stage's reads and the smoothed speed (docs/decisions/0007-reading-and-writing-in-chunks.md)


@pytest.mark.parametrize("window", [1, 2, 3, 4, 5, 7, 9])
def test_the_shrinking_running_median_is_polars_bit_for_bit(window: int) -> None:
    rng = np.random.default_rng(window)
    for n in [0, 1, 2, window - 1, window, 2 * window - 1, 2 * window, 2 * window + 1, 50, 997]:
        values = np.round(rng.normal(60.0, 25.0, max(n, 0)), 1)
        values[rng.random(values.size) < 0.3] = 0.0  # ties, as a stopped wagon's GPS gives
        values[rng.random(values.size) < 0.1] = 61.3
        expected = (
            pl.Series(values, dtype=pl.Float64)
            .rolling_median(window_size=window, center=True, min_samples=1)
            .to_numpy()
        )
        got = shrinking_running_median(values, window)
        assert got.dtype == np.float64 and got.shape == expected.shape
        assert np.array_equal(got, expected), (window, n)


def _two_wagons_overlapping(fleet: Path) -> list[str]:
    """Two wagons, each with chains of files apart and files overlapping in time (the same
    seconds logged twice: the chunk's rows are not in time order by file)."""
    wagons = [WAGON, "SGG-0002"]
    write_registry(fleet, wagons)
    rng = np.random.default_rng(11)
    for w, wagon in enumerate(wagons):
        for k in range(3):
            start = T0_UTC + dt.timedelta(hours=2 * k, minutes=7 * w)
            frame = make_session(rng, start, n_events=3).frame
            write_session(fleet, wagon, frame, start)
            if k == 1:  # the middle of the session again, in a second file
                late = frame.slice(frame.height // 3, frame.height // 3)
                write_session(fleet, wagon, late, late["time_utc"][0])
    return wagons


def test_a_chunk_of_windows_reads_each_as_the_per_window_query(tmp_path: Path) -> None:
    from fleetbrake.warehouse.connection import open_warehouse, sql

    fleet, db = tmp_path / "fleet", tmp_path / "fleet.duckdb"
    wagons = _two_wagons_overlapping(fleet)
    run_ingest(fleet, db, progress=False)
    config = EventConfig()
    with open_warehouse(db, read_only=True) as wh:
        files = wh.con.execute(sql("q_events_files"), {"wagon_ids": wagons}).fetchall()
        windows = []
        for wagon in [*wagons, "SGG-0404"]:  # the last: a window of no samples
            spans = [(a, b) for w, a, b, _ in files if w == wagon] or [(T0_UTC, T0_UTC)]
            chains = tuple((a, b) for a, b in spans)
            windows += [
                events_module._Window(wagon, chains, 1, last=False),  # the whole wagon
                events_module._Window(wagon, chains[1:2] or chains, 1, last=True),
            ]
        windows.insert(1, events_module._Window(WAGON, (), 0, last=False))  # nothing to read
        task = events_module._chunk_task(wh, windows, config)
        assert task.samples is not None
        stored_order = task.samples.column("time_utc").to_numpy()
        assert not np.all(np.diff(stored_order) > np.timedelta64(0))  # the sort is exercised
        reading = [w for w in windows if w.chains]
        parts = events_module._window_parts(task.samples, len(reading))
        for window, part in zip(reading, parts, strict=True):
            params = {
                "wagon_id": window.wagon_id,
                "from_utc": window.chains[0][0],
                "to_utc": window.chains[-1][1],
            }
            expected = wh.con.sql(sql("q_event_samples"), params=params).pl()
            assert part.schema == expected.schema
            assert part.equals(expected), window
        assert sum(p.height for p in parts) == task.samples.num_rows
        assert parts[-1].is_empty() and parts[-2].is_empty()


@pytest.mark.parametrize("load_rows", [1, 60_000])
def test_chunks_of_several_wagons_give_each_wagons_events(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, load_rows: int
) -> None:
    fleet = tmp_path / "fleet"
    _two_wagons_overlapping(fleet)
    whole = run_ingest(fleet, tmp_path / "a.duckdb", progress=False)  # both wagons, one chunk
    monkeypatch.setattr(events_module, "_LOAD_ROWS", load_rows)  # each chain alone; or pairs
    apart = run_ingest(fleet, tmp_path / "b.duckdb", progress=False)
    assert whole.events is not None and apart.events is not None
    assert whole.events.wagons == apart.events.wagons == 2
    assert whole.events.chains == apart.events.chains == 6
    expected = _events(tmp_path / "a.duckdb").drop("detected_utc")
    assert expected.height >= 12 and expected["wagon_id"].n_unique() == 2
    assert _events(tmp_path / "b.duckdb").drop("detected_utc").equals(expected)
    by_wagon = pl.concat(
        [
            detect_events(  # each wagon's events from its samples alone, no warehouse
                _samples_of(tmp_path / "a.duckdb", wagon), wagon
            )
            for wagon in [WAGON, "SGG-0002"]
        ]
    ).sort("start_utc")
    assert by_wagon.select(expected.columns).equals(expected.select(expected.columns))


def _samples_of(db: Path, wagon: str) -> pl.DataFrame:
    con = duckdb.connect(str(db), read_only=True)
    try:
        return con.sql(
            "SELECT time_utc, file_id, speed_kmh, distance_m, brake_pressure_bar, block_temp_c, "
            "block_temp_fault FROM samples WHERE wagon_id = $w ORDER BY time_utc, file_id",
            params={"w": wagon},
        ).pl()
    finally:
        con.close()
