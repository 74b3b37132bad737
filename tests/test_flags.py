"""Tests of fleetbrake.flags: each detector on hand-made series, the configuration file, the
flags table, and end to end on generated fleets against the generator's truth."""

from __future__ import annotations

import dataclasses
import datetime as dt
import itertools
import os
import re
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from fleetbrake.flags import (
    CONFIG_KEYS,
    EventStat,
    Finding,
    Flag,
    FlagConfig,
    FlagConfigError,
    Segment,
    event_stats,
    find_dragging,
    find_drift,
    find_dropouts,
    find_frozen,
    find_loose,
    find_out_of_range,
    find_overheating,
    find_weak,
    heat_flow_corrected,
    load_flag_config,
    merge_sensor_faults,
    raise_flags,
    same_readings,
    segment_stats,
)
from fleetbrake.simulation.chains import ChainParams, segment_bounds
from fleetbrake.simulation.series import WagonSeries

T0 = dt.datetime(2024, 3, 4, 8, 0, 0)
DOCS = Path(__file__).resolve().parents[1] / "docs" / "flags.md"


# --------------------------------------------------------------------------------------------
# Hand-made series


def make_series(
    measured: np.ndarray,
    *,
    speed: float | np.ndarray = 70.0,
    pressure: float | np.ndarray = 0.0,
    ambient: float = 10.0,
    fault: np.ndarray | None = None,
    raw: np.ndarray | None = None,
    drop: np.ndarray | None = None,
    events: list[tuple[str, int, int]] = (),  # type: ignore[assignment]
    wagon_id: str = "TEST-0001",
) -> WagonSeries:
    """A 1 Hz series from ``T0`` (rows where ``drop`` is set are not written at all)."""
    n = measured.size
    frame = pl.DataFrame(
        {
            "time_utc": pl.Series([T0 + dt.timedelta(seconds=k) for k in range(n)]),
            "speed_kmh": np.broadcast_to(np.asarray(speed, dtype=float), n).copy(),
            "brake_pressure_bar": np.broadcast_to(np.asarray(pressure, dtype=float), n).copy(),
            "block_temp_c": np.where(np.isfinite(measured), measured, np.nan),
            "block_temp_fault": np.zeros(n, dtype=bool) if fault is None else fault,
            "block_temp_raw_c": np.full(n, np.nan) if raw is None else raw,
            "ambient_temp_c": np.full(n, ambient),
        }
    ).with_columns(pl.col("block_temp_c").fill_nan(None))
    if drop is not None:
        frame = frame.filter(pl.Series(~drop))
    event_frame = pl.DataFrame(
        {
            "event_id": [e[0] for e in events],
            "start_utc": pl.Series([T0 + dt.timedelta(seconds=e[1]) for e in events]),
            "end_utc": pl.Series([T0 + dt.timedelta(seconds=e[2]) for e in events]),
        },
        schema={
            "event_id": pl.String,
            "start_utc": pl.Datetime("us"),
            "end_utc": pl.Datetime("us"),
        },
    )
    return WagonSeries.from_frame(wagon_id, frame, ambient_default_c=ambient, events=event_frame)


def noisy(values: np.ndarray, seed: int = 0, sigma: float = 0.1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.round(values + rng.normal(0.0, sigma, values.size), 2)


def segments_of(
    series: WagonSeries, predicted: np.ndarray, config: FlagConfig | None = None
) -> list[Segment]:
    config = config or FlagConfig()
    bounds, kinds = segment_bounds(series, ChainParams())
    return segment_stats(series, predicted, bounds, kinds, config)


def at(seconds: float) -> dt.datetime:
    return T0 + dt.timedelta(seconds=seconds)


# --------------------------------------------------------------------------------------------
# Configuration


def test_config_defaults_are_valid_and_bad_values_are_named() -> None:
    config = FlagConfig()
    assert config.contact_limit_c == 400.0 and config.weak_ratio == 0.75
    with pytest.raises(ValueError, match=r"weak_ratio must be > 0, got 0 \(an integer\)"):
        FlagConfig(weak_ratio=0)
    with pytest.raises(ValueError, match=r"frozen_min_s must be an integer, got 1.5"):
        FlagConfig(frozen_min_s=1.5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="weak_alarm_ratio must not exceed weak_ratio"):
        FlagConfig(weak_alarm_ratio=0.8)
    with pytest.raises(ValueError, match="detached_ratio must be in"):
        FlagConfig(detached_ratio=1.5)
    assert isinstance(FlagConfig(contact_limit_c=380).contact_limit_c, float)


def test_load_flag_config_reads_the_keys_a_file_sets(tmp_path: Path) -> None:
    path = tmp_path / "flags.toml"
    path.write_text(
        "# fleet engineer's thresholds\ncontact_limit_c = 380   # degC\nweak_ratio = 0.7\n"
        "frozen_min_s = 300\n",
        encoding="utf-8",
    )
    config = load_flag_config(path)
    assert config == dataclasses.replace(
        FlagConfig(), contact_limit_c=380.0, weak_ratio=0.7, frozen_min_s=300
    )
    empty = tmp_path / "empty.toml"
    empty.write_text("", encoding="utf-8")
    assert load_flag_config(empty) == FlagConfig()


def test_config_key_is_its_content_alone(tmp_path: Path) -> None:
    """``FlagConfig.key()`` (stored with each span's judgement in ``flagged_spans``) is the
    same for the same thresholds however they were given, another for any other threshold,
    and stable across processes (a hash of the names and values, not Python's ``hash``)."""
    import subprocess
    import sys

    path = tmp_path / "flags.toml"
    path.write_text("contact_limit_c = 400\n", encoding="utf-8")  # the default, as an integer
    key = FlagConfig().key()
    assert len(key) == 64 and load_flag_config(path).key() == key
    assert FlagConfig(contact_limit_c=400).key() == key
    changed = {
        FlagConfig(contact_limit_c=380.0).key(),
        FlagConfig(frozen_min_s=121).key(),
        FlagConfig(estimator=False).key(),
        FlagConfig().scaled(1.0).key(),
    }
    assert key not in changed and len(changed) == 4
    other_process = subprocess.run(
        [
            sys.executable,
            "-c",
            "from fleetbrake.flags import FlagConfig; print(FlagConfig().key())",
        ],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "PYTHONHASHSEED": "12345"},
    )
    assert other_process.stdout.strip() == key


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("weak_ration = 0.7\n", r"key weak_ration: unknown key \(did you mean weak_ratio\?\)"),
        ('frozen_min_s = "120"\n', r'key frozen_min_s: must be an integer, got "120" \(a string\)'),
        ("contact_limit_c = true\n", r"key contact_limit_c: must be a number, got true"),
        ("contact_limit_c = -5.0\n", r"key contact_limit_c: must be in \(0, 1500\) degC"),
        ("[weak]\nratio = 0.7\n", r"key weak: unknown key"),
        ("weak_alarm_ratio = 0.9\n", r"weak_alarm_ratio must not exceed weak_ratio"),
        ("weak_ratio = \n", r"not a valid TOML file"),
    ],
)
def test_load_flag_config_names_the_file_and_key(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "flags.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(FlagConfigError, match=re.escape(str(path)) + ": .*" + message):
        load_flag_config(path)


def test_keys_that_moved_to_the_simulation_say_where(tmp_path: Path) -> None:
    path = tmp_path / "flags.toml"
    path.write_text("after_release_s = 120\n", encoding="utf-8")
    with pytest.raises(
        FlagConfigError,
        match=r"key after_release_s: no longer a flag threshold: .*ChainParams\.quiet_after_release_s",
    ):
        load_flag_config(path)


def test_a_toml_override_of_a_named_threshold_changes_a_detector(tmp_path: Path) -> None:
    """Every threshold of the detectors is a key like any other: here the
    pairs of readings a frozen sensor's noise is judged from, and the speed above which a data
    gap may hide brakings."""
    n = 3000
    measured = noisy(np.linspace(30.0, 25.0, n))
    measured[1000:1400] = measured[1000]
    series = make_series(measured)
    assert len(find_frozen(series)) == 1
    path = tmp_path / "flags.toml"
    path.write_text("frozen_noise_min_pairs = 5000\n", encoding="utf-8")
    assert find_frozen(series, load_flag_config(path)) == []
    # a gap at 4 km/h: a standing wagon by default, a moving one below 3 km/h
    from fleetbrake.flags import unsure_mask

    slow = make_series(noisy(np.full(n, 20.0)), speed=4.0)
    assert not unsure_mask(slow, [(999, 1100)]).any()
    path.write_text("gap_moving_speed_kmh = 3.0\n", encoding="utf-8")
    assert unsure_mask(slow, [(999, 1100)], load_flag_config(path))[999:2000].all()


def test_load_flag_config_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FlagConfigError, match=r"nope\.toml: flag configuration file not found"):
        load_flag_config(tmp_path / "nope.toml")


def test_docs_describe_every_threshold() -> None:
    text = DOCS.read_text(encoding="utf-8")
    missing = [key for key in CONFIG_KEYS if f"`{key}`" not in text]
    assert not missing, f"docs/flags.md does not describe {missing}"


# --------------------------------------------------------------------------------------------
# Sensor faults from the readings


def test_out_of_range_runs_merge_and_name_the_reading() -> None:
    n = 2000
    fault = np.zeros(n, dtype=bool)
    fault[500:600] = True
    fault[650:700] = True  # 50 s later: the same broken wire
    fault[1500:1505] = True
    raw = np.where(fault, 1150.0, np.nan)
    raw[1500:1505] = -230.0
    measured = np.where(fault, np.nan, noisy(np.full(n, 20.0)))
    found = find_out_of_range(make_series(measured, fault=fault, raw=raw))
    assert [(f.start_utc, f.end_utc, f.severity) for f in found] == [
        (at(500), at(700), "warning"),
        (at(1500), at(1505), "info"),
    ]
    assert all(f.kind == "sensor_fault" and f.detail == "out_of_range" for f in found)
    assert "read 1150.0 °C, above the 600 °C" in found[0].evidence
    assert "open circuit" in found[0].evidence and "TEST-0001" in found[0].evidence
    assert "between 08:08:20 and 08:11:40 UTC" in found[0].evidence
    assert "below the -60 °C" in found[1].evidence and "short circuit" in found[1].evidence


def test_frozen_reading_found_by_its_missing_noise() -> None:
    n = 3000
    measured = noisy(np.linspace(30.0, 25.0, n))
    measured[1000:1400] = measured[1000]
    measured[2000:2060] = measured[2000]  # one minute: too short to judge
    found = find_frozen(make_series(measured))
    assert len(found) == 1
    (f,) = found
    assert (f.start_utc, f.end_utc, f.detail) == (at(1000), at(1400), "frozen")
    assert f"stuck at {measured[1000]:.2f} °C for 6 min 40 s" in f.evidence
    assert re.search(r"scatter by ±0\.(09|1\d) K elsewhere", f.evidence)


def test_frozen_needs_the_model_when_the_sensor_is_quiet() -> None:
    n = 2000
    steady = np.full(n, 18.00)  # a noise-free sensor on a block at rest: constant, and right
    series = make_series(steady)
    assert find_frozen(series) == []
    assert find_frozen(series, predicted_c=np.full(n, 18.0)) == []
    cooling = np.linspace(24.0, 18.0, n)  # the model has the block cool by 6 K meanwhile
    (f,) = find_frozen(series, predicted_c=cooling)
    assert "the model has the block change by -6.0 K" in f.evidence


def test_dropouts_are_missing_readings_in_rows_that_are_there() -> None:
    n = 3000
    measured = noisy(np.full(n, 20.0))
    measured[500:620] = np.nan  # 2 min of empty cells
    measured[1000:1030] = np.nan  # half a minute: not a dropout
    drop = np.zeros(n, dtype=bool)
    drop[2000:2600] = True  # no rows at all: a gap of the logger, not of the sensor
    found = find_dropouts(make_series(measured, drop=drop))
    assert [(f.start_utc, f.end_utc, f.detail) for f in found] == [(at(500), at(620), "dropout")]
    assert "missing for 2 min" in found[0].evidence


# --------------------------------------------------------------------------------------------
# Against the model (hand-made predictions)


def test_dragging_window_heats_while_the_model_cools() -> None:
    n = 4200
    predicted = np.linspace(40.0, 36.0, n)  # no pressure: the block cools
    drag = np.clip((np.arange(n) - 1800) / 1800.0, 0.0, 1.0) * 15.0  # +15 K from t = 1800 s
    series = make_series(noisy(predicted + drag), speed=72.0)
    (f,) = find_dragging(series, segments_of(series, predicted))
    assert f.kind == "dragging_brake" and f.detail == "no_pressure"
    assert (f.start_utc, f.end_utc) == (at(1800), at(3600))  # the windows that heated
    assert re.search(
        r"heated \d+\.\d K .* at 72 km/h on average\) with at most 0\.00 bar", f.evidence
    )
    assert "the model predicts cooling by" in f.evidence and "dragging brake" in f.evidence
    # standing still nothing can drag; a sensor fault over the windows hides them
    standing = make_series(noisy(predicted + drag), speed=0.0)
    assert find_dragging(standing, segments_of(standing, predicted)) == []
    assert find_dragging(series, segments_of(series, predicted), excluded=[(0, n)]) == []
    # the model's own heating is no drag
    assert find_dragging(series, segments_of(series, predicted + drag)) == []


def test_segments_left_the_same_readings_are_the_same_segments() -> None:
    """The flags skip a span's second ``segment_stats`` when the sensor faults leave out no
    further reading (``same_readings``): masking seconds that hold no finite reading changes no
    segment; masking one that does is seen."""
    n = 4200
    predicted = np.linspace(40.0, 36.0, n)
    measured = noisy(predicted + np.clip((np.arange(n) - 1800) / 1800.0, 0.0, 1.0) * 15.0)
    measured[1000:1100] = np.nan  # a dropout
    series = make_series(measured, speed=72.0)
    bounds, kinds = segment_bounds(series, ChainParams())
    config = FlagConfig()
    broken = ~np.isfinite(series.measured_c)
    wider = broken.copy()
    wider[1000:1100] = True  # the dropout again: no reading there
    assert same_readings(series, broken, wider)
    first = segment_stats(series, predicted, bounds, kinds, config, invalid=broken)
    again = segment_stats(series, predicted, bounds, kinds, config, invalid=wider)
    assert repr(first) == repr(again)  # bit for bit, NaN included
    wider[2000:2300] = True  # a fault over readings that are there
    assert not same_readings(series, broken, wider)
    assert repr(segment_stats(series, predicted, bounds, kinds, config, invalid=wider)) != repr(
        first
    )


def test_loose_sensor_falls_to_the_air() -> None:
    n, onset = 5400, 1900
    predicted = np.linspace(45.0, 40.0, n)
    measured = predicted.copy()
    t = np.arange(n - onset)
    measured[onset:] = 10.0 + (predicted[onset:] - 10.0) * np.exp(-t / 400.0)
    series = make_series(noisy(measured), ambient=10.0)
    (f,) = find_loose(series, segments_of(series, predicted), predicted_c=predicted)
    assert f.detail == "loose" and at(onset - 60) <= f.start_utc <= at(onset + 30)
    assert f.end_utc == at(n)
    assert "towards the 10.0 °C air" in f.evidence and "loose" in f.evidence
    # a reading rising less than the model is no loose sensor
    rising = make_series(noisy(np.linspace(18.0, 21.0, n)), ambient=6.0)
    assert find_loose(rising, segments_of(rising, np.linspace(18.0, 29.0, n))) == []


def test_drift_is_a_steady_trend_no_heat_flow_explains() -> None:
    n = 7200
    predicted = np.full(n, 30.0)  # a settled block
    offset = np.clip(np.arange(n) - 1200, 0, None) * 6.0 / 3600.0  # +6 K/h from t = 1200 s
    series = make_series(noisy(predicted + offset))
    (f,) = find_drift(series, segments_of(series, predicted))
    assert f.detail == "drift" and f.start_utc <= at(1800) and f.end_utc == at(n)
    assert "drifted away from the model at +6.0 K/h" in f.evidence
    negative = make_series(noisy(predicted - offset))
    (g,) = find_drift(negative, segments_of(negative, predicted))
    assert "at -6.0 K/h" in g.evidence
    # a block cooling faster than the model in proportion to its excess over the air is a heat
    # flow the model has wrong, not a drift
    truth = 10.0 + 40.0 * np.exp(-np.arange(n) / 3000.0)
    cooling = make_series(noisy(truth), ambient=10.0)
    bounds, _ = segment_bounds(cooling, ChainParams())
    model = np.empty(n)  # re-anchored at each window, as the watch simulation does
    for a, b in itertools.pairwise(bounds):
        model[a:b] = 10.0 + (truth[a] - 10.0) * np.exp(-np.arange(b - a) / 5000.0)
    assert find_drift(cooling, segments_of(cooling, model)) == []
    # no trend, no drift
    flat = make_series(noisy(predicted))
    assert find_drift(flat, segments_of(flat, predicted)) == []


def window(k: int, excess: float, slope: float, speed: float = 80.0) -> Segment:
    """A settled quiet window of 600 s, 10 degC air, the block ``excess`` above it."""
    return Segment(
        start=600 * k,
        stop=600 * (k + 1),
        kind="quiet",
        enough=True,
        calm=True,
        event_id=None,
        speed_kmh=speed,
        pressure_max_bar=0.0,
        ambient_c=10.0,
        m_start=10.0 + excess,
        m_end=10.0 + excess + slope / 6.0,
        p_start=10.0 + excess,
        p_end=10.0 + excess,
        m_rise=0.0,
        p_rise=0.0,
        slope_k_per_h=slope,
        line_rms_k=0.1,
        since_release_s=3600.0,
        m_ambient_k=excess,
    )


def test_a_drift_after_a_data_gap_is_caught_when_the_reading_leaves_the_model() -> None:
    """After a data gap in which the wagon may have braked the block is unsure (its windows
    not ``calm``): hidden heat leaves the reading above the model and converging back to it,
    which is no drift; a reading that keeps leaving the model is one all the same (an
    acceptance fleet's 32-minute drift began 2 minutes after such a gap)."""
    n = 7200
    predicted = np.full(n, 30.0)

    def unsure(series: WagonSeries) -> list[Segment]:
        # every window after t = 600 s under the gap's unsure span
        return [
            dataclasses.replace(s, calm=False) if s.start >= 600 else s
            for s in segments_of(series, predicted)
        ]

    offset = np.clip(np.arange(n) - 1200, 0, None) * 6.0 / 3600.0  # +6 K/h from t = 1200 s
    drifting = make_series(noisy(predicted + offset))
    windows = unsure(drifting)
    assert not any(s.judged for s in windows if s.start >= 600)
    (f,) = find_drift(drifting, windows)
    assert f.detail == "drift" and "at +6.0 K/h" in f.evidence
    # the heat a gap hid: 3 K above the model, falling back to it (at first 7 K/h)
    hidden = 3.0 * np.exp(-np.clip(np.arange(n) - 600, 0, None) / 1500.0)
    hidden[:600] = 0.0
    converging = make_series(noisy(predicted + hidden))
    assert find_drift(converging, unsure(converging)) == []


def test_a_heat_flow_the_model_has_wrong_is_taken_out_before_drifts_are_judged() -> None:
    rng = np.random.default_rng(3)
    excess = rng.uniform(5.0, 80.0, 40)
    # the block cools faster than the model says, the more the hotter and the faster it runs
    windows = [
        window(k, e, -e * (0.05 + 0.1 * 0.8) + rng.normal(0.0, 0.2), speed=80.0)
        for k, e in enumerate(excess)
    ]
    drifting = {20, 21, 22, 23, 24}
    windows = [
        dataclasses.replace(w, slope_k_per_h=w.slope_k_per_h + 6.0) if k in drifting else w
        for k, w in enumerate(windows)
    ]
    corrected = heat_flow_corrected(windows)
    rates = np.array([w.slope_k_per_h for w in corrected])
    assert np.all(np.abs(np.delete(rates, list(drifting))) < 1.0)
    assert np.all(np.abs(rates[list(drifting)] - 6.0) < 1.0)
    # a model with no such error is left alone
    clean = [window(k, e, rng.normal(0.0, 0.2)) for k, e in enumerate(excess)]
    assert heat_flow_corrected(clean) == clean


def day_windows(days: int, rate_at: dict[int, float]) -> tuple[WagonSeries, list[Segment]]:
    """``days`` days of settled quiet windows (600 s, from ``T0``, 08:00 UTC), the block 30 K
    above the air; window k's measured - predicted changes at ``rate_at.get(k, 0)`` K/h plus
    a little noise."""
    rng = np.random.default_rng(5)
    count = days * 144
    series = make_series(np.full(600 * count, 40.0))
    windows = [window(k, 30.0, rate_at.get(k, 0.0) + rng.normal(0.0, 0.2)) for k in range(count)]
    return series, windows


def sunny(k: int) -> bool:
    """Window k (from 08:00) lies between 09:00 and 13:00 UTC."""
    return 6 <= k % 144 < 30


def test_a_misfit_that_comes_back_at_the_same_hour_every_day_is_no_drift() -> None:
    """Sunshine the model lacks: measured - predicted rises at +3.5 K/h every day from 09:00
    to 13:00 and not otherwise. A drift happens once; this comes and goes with the hour of
    day: a model error, not a sensor fault."""
    series, windows = day_windows(3, {k: 3.5 for k in range(3 * 144) if sunny(k)})
    assert find_drift(series, windows) == []
    # one day of data cannot tell: a drift stays a drift
    one_day, windows = day_windows(1, {k: 3.5 for k in range(144) if sunny(k)})
    (f,) = find_drift(one_day, windows)
    assert f.detail == "drift"
    # the same trend on one day only, at that hour: a drift
    once, windows = day_windows(3, {k: 3.5 for k in range(144, 2 * 144) if sunny(k)})
    (g,) = find_drift(once, windows)
    assert g.start_utc.date() == (T0 + dt.timedelta(days=1)).date()


def test_a_drift_growing_in_time_is_not_taken_for_a_heat_flow() -> None:
    """The block warms over the run while the offset grows: the rates follow the excess over
    the air, but they follow the time better still, as a growing offset's do."""
    hot = [window(k, 40.0 + 8.0 * k, 3.0 + 0.9 * k) for k in range(8)]
    hot[3] = dataclasses.replace(hot[3], p_start=10.0 + 90.0, p_end=10.0 + 90.0)  # a hot one
    series = make_series(np.full(600 * 8, 40.0))
    (f,) = find_drift(series, hot)
    assert f.detail == "drift"
    # rates that follow the block's excess and not the time: a heat flow
    scattered = [window(k, e, 0.08 * e) for k, e in enumerate([40, 90, 50, 100, 45, 95, 55, 85])]
    assert find_drift(series, scattered) == []


def test_drift_between_frequent_brakings_must_show_in_them_too() -> None:
    n, period = 6000, 720
    events = [(f"E{k}", k, k + 60) for k in range(600, n - 300, period)]
    pressure = np.zeros(n)
    for _, a, b in events:
        pressure[a:b] = 1.2
    predicted = np.full(n, 30.0)
    offset = np.clip(np.arange(n) - 600, 0, None) * 6.0 / 3600.0  # from the first braking on
    series = make_series(noisy(predicted + offset), pressure=pressure, events=events)
    (f,) = find_drift(series, segments_of(series, predicted))
    assert "as much as between them" in f.evidence  # no window long after a braking
    # the same trend between brakings in which the block falls behind the model (a weak
    # brake's aftermath): no drift
    behind = predicted + offset
    for _, a, _ in events:
        behind[a : a + 180] -= np.linspace(0.0, 4.0, 180)
        behind[a + 180 :] -= 4.0
    weak = make_series(noisy(behind), pressure=pressure, events=events)
    assert find_drift(weak, segments_of(weak, predicted)) == []


def test_braking_heating_far_above_the_prediction_is_dragging() -> None:
    series = make_series(noisy(np.full(3600, 20.0)))
    hot = dataclasses.replace(stat(0, 2.0), event_id="E-hot")
    (f,) = find_dragging(series, [], [hot, stat(1, 1.1)])
    assert (f.detail, f.event_id, f.start_utc) == ("braking", "E-hot", hot.start_utc)
    assert "heated 20.0 K in the braking" in f.evidence and "10.0 K were predicted" in f.evidence
    assert find_dragging(series, [], [stat(0, 1.4)]) == []  # 1.4 x: not far enough above


def stat(k: int, ratio: float, *, judged: bool = True, p_rise: float = 10.0) -> EventStat:
    start = at(3600 * k)
    return EventStat(
        event_id=f"TEST-0001-{start:%Y%m%dT%H%M%S}",
        start_utc=start,
        end_utc=start + dt.timedelta(seconds=60),
        window_end_utc=start + dt.timedelta(seconds=660),
        judged=judged,
        m_rise=ratio * p_rise,
        p_rise=p_rise,
        contact_max_c=150.0,
        contact_max_utc=start + dt.timedelta(seconds=50),
        v_start_kmh=80.0,
        v_end_kmh=40.0,
        p_max_bar=1.4,
    )


def test_weak_brakings_in_a_row_are_one_flag() -> None:
    stats = [
        stat(0, 1.01),
        stat(1, 0.55),
        stat(2, 0.1, judged=False),  # not judged: neither counts nor breaks the run
        stat(3, 0.62),
        stat(4, 0.2, p_rise=0.5),  # too small a predicted rise to judge
        stat(5, 0.58),
        stat(6, 0.99),  # a normal braking ends the run
        stat(7, 0.4),  # alone: no flag
    ]
    (f,) = find_weak("TEST-0001", stats)
    assert (f.kind, f.severity, f.start_utc, f.end_utc) == (
        "weak_brake",
        "warning",
        stats[1].start_utc,
        stats[5].end_utc,
    )
    assert f.event_id is None
    assert "heated only 58 % of the predicted rise in 3 brakings" in f.evidence
    assert "5.5 K instead of 10.0 K" in f.evidence and "1.40 bar" in f.evidence
    (g,) = find_weak("TEST-0001", [stat(0, 0.45), stat(1, 0.3)])
    assert g.severity == "alarm"
    (single,) = find_weak("TEST-0001", [stat(0, 0.5)], FlagConfig(weak_min_events=1))
    assert single.event_id == stats[0].event_id


def test_overheating_severity_by_margin() -> None:
    stats = [
        dataclasses.replace(stat(k, 1.0), contact_max_c=c)
        for k, c in enumerate((390.0, 410.0, 450.0, 520.0))
    ]
    found = find_overheating("TEST-0001", stats)
    assert [f.severity for f in found] == ["info", "warning", "alarm"]
    assert [f.event_id for f in found] == [s.event_id for s in stats[1:]]
    assert "reached 520 °C" in found[-1].evidence and "over the 400 °C limit" in found[-1].evidence
    assert find_overheating("TEST-0001", stats, FlagConfig(contact_limit_c=600.0)) == []


def test_event_stats_measure_rises_and_leave_out_faults() -> None:
    n = 700
    p = 20.0 + 10.0 * np.clip(np.arange(n) / 60.0, 0.0, 1.0)
    m = 20.0 + 5.0 * np.clip(np.arange(n) / 60.0, 0.0, 1.0)
    predictions = pl.DataFrame(
        {
            "event_id": "E1",
            "time_utc": pl.Series([at(k) for k in range(n)]),
            "phase": ["heating" if k <= 60 else "cooling" for k in range(n)],
            "measured_sensor_c": noisy(m),
            "predicted_sensor_c": p,
            "predicted_contact_max_c": p + 100.0,
            "speed_kmh": np.linspace(80.0, 40.0, n),
            "brake_pressure_bar": np.where(np.arange(n) <= 60, 1.2, 0.0),
        }
    )
    events = pl.DataFrame(
        {"event_id": ["E1"], "start_utc": [at(0)], "end_utc": [at(60)], "complete": [True]}
    )
    (e,) = event_stats(predictions, events)
    assert e.judged and abs(e.p_rise - 10.0) < 1e-9 and abs(e.ratio - 0.5) < 0.05
    assert e.contact_max_c == pytest.approx(130.0) and e.p_max_bar == pytest.approx(1.2)
    (x,) = event_stats(predictions, events, excluded=[(at(300), at(400))])
    assert not x.judged
    (u,) = event_stats(predictions, events.with_columns(complete=pl.lit(False)))
    assert not u.judged


def test_sensor_faults_close_together_are_one_flag() -> None:
    def fault(a: int, b: int, detail: str) -> Finding:
        return Finding(
            "sensor_fault", "warning", at(a), at(b), f"{detail}.", detail=detail, summary=detail
        )

    merged = merge_sensor_faults(
        [fault(0, 1000, "loose"), fault(1300, 1500, "frozen"), fault(9000, 9100, "frozen")]
    )
    assert [(f.start_utc, f.end_utc, f.detail) for f in merged] == [
        (at(0), at(1500), "loose"),
        (at(9000), at(9100), "frozen"),
    ]
    assert "also frozen" in merged[0].evidence


# --------------------------------------------------------------------------------------------
# The flags table


def _warehouse_with_samples(tmp_path: Path) -> tuple[object, object]:
    from fleetbrake.fleet.registry import load_registry
    from fleetbrake.ingest.spans import update_spans
    from fleetbrake.simulation.predictions import ensure_declared
    from fleetbrake.warehouse.connection import open_warehouse

    (tmp_path / "fleet.toml").write_text("[defaults]\nambient_temp_c = 8.0\n", encoding="utf-8")
    registry = load_registry(tmp_path / "fleet.toml")
    wh = open_warehouse(tmp_path / "fleet.duckdb")
    ensure_declared(wh)
    n = 2400
    measured = noisy(np.full(n, 15.0))
    fault = np.zeros(n, dtype=bool)
    fault[300:420] = True
    measured[1500:1600] = np.nan
    for file_id, wagon_id in enumerate(("UNREG-1", "UNREG-2"), start=1):
        wh.con.execute(  # the file the samples came from: the spans are cut from the files
            "INSERT INTO files (file_id, path, wagon_id, sha256, size_bytes, mtime_ns, status, "
            "rows, first_utc, last_utc, ingested_utc) VALUES ($f, $p, $w, 'x', 1, 1, "
            "'ingested', $n, $a, $b, $a)",
            {"f": file_id, "p": f"logs/{wagon_id}.csv", "w": wagon_id, "n": n, "a": at(0)}
            | {"b": at(n - 1)},
        )
        frame = pl.DataFrame(
            {
                "wagon_id": wagon_id,
                "file_id": file_id,
                "time_utc": pl.Series([at(k) for k in range(n)]),
                "speed_kmh": 50.0,
                "distance_m": None,
                "elevation_m": None,
                "lat_deg": None,
                "lon_deg": None,
                "brake_pressure_bar": 0.0,
                "block_temp_c": np.where(fault, np.nan, measured),
                "block_temp_raw_c": np.where(fault, 999.0, np.nan),
                "block_temp_fault": fault,
                "ambient_temp_c": 8.0,
            }
        ).with_columns(pl.col("block_temp_c").fill_nan(None))
        wh.con.register("fb_test", frame)
        wh.con.execute("INSERT INTO samples SELECT * FROM fb_test")
        wh.con.unregister("fb_test")
    update_spans(wh)
    return wh, registry


def test_raise_flags_replaces_a_wagons_flags_with_stable_ids(tmp_path: Path) -> None:
    from fleetbrake.ingest.spans import update_spans

    wh, registry = _warehouse_with_samples(tmp_path)
    try:
        report = raise_flags(wh, registry, "declared")  # type: ignore[arg-type]
        assert report.wagons == ["UNREG-1", "UNREG-2"]
        assert any("UNREG-1: no valid registry entry" in note for note in report.notes)
        ids = sorted(f.flag_id for f in report.flags)
        assert ids == [
            "sensor_fault-UNREG-1-20240304T080500",
            "sensor_fault-UNREG-1-20240304T082500",
            "sensor_fault-UNREG-2-20240304T080500",
            "sensor_fault-UNREG-2-20240304T082500",
        ]
        rows = wh.con.execute(  # type: ignore[attr-defined]
            "SELECT flag_id, kind, severity, evidence FROM v_flags ORDER BY flag_id"
        ).fetchall()
        assert [r[0] for r in rows] == ids
        first = wh.con.execute("SELECT flag_id, detected_utc FROM flags ORDER BY 1").fetchall()  # type: ignore[attr-defined]
        # again: the same flags, their detected_utc kept
        again = raise_flags(wh, registry, "declared")  # type: ignore[arg-type]
        assert [f.flag_id for f in again.flags] == [f.flag_id for f in report.flags]
        assert (
            wh.con.execute("SELECT flag_id, detected_utc FROM flags ORDER BY 1").fetchall() == first
        )  # type: ignore[attr-defined]
        # one wagon's file and samples gone: only its flags go
        wh.con.execute("DELETE FROM samples WHERE wagon_id = 'UNREG-2'")  # type: ignore[attr-defined]
        wh.con.execute("DELETE FROM files WHERE wagon_id = 'UNREG-2'")  # type: ignore[attr-defined]
        update_spans(wh)  # type: ignore[arg-type]
        raise_flags(wh, registry, "declared", wagons=["UNREG-2"])  # type: ignore[arg-type]
        left = wh.con.execute("SELECT DISTINCT wagon_id FROM flags").fetchall()  # type: ignore[attr-defined]
        assert left == [("UNREG-1",)]
    finally:
        wh.close()  # type: ignore[attr-defined]


def test_flag_ids_are_unique_for_flags_starting_together() -> None:
    from fleetbrake.flags import flag_ids

    same = Finding("sensor_fault", "info", at(0), at(10), "a.")
    flags = flag_ids("W-1", [same, dataclasses.replace(same, evidence="b.")])
    assert [f.flag_id for f in flags] == [
        "sensor_fault-W-1-20240304T080000",
        "sensor_fault-W-1-20240304T080000-2",
    ]
    assert all(isinstance(f, Flag) for f in flags)


# --------------------------------------------------------------------------------------------
# End to end on generated fleets


@dataclasses.dataclass
class Outcome:
    name: str
    flags: list[Flag]
    truth: object
    observable: dict[int, bool]
    seconds: dict[str, float]


@pytest.fixture(scope="module")
def run_fleet(
    tmp_path_factory: pytest.TempPathFactory,
    reduced_model_for: Callable[..., object],
    rom_cache_dir: Path,
) -> Iterator[Callable[..., Outcome]]:
    """``run_fleet(seed=, wagons=, days=, anomalies=)``: generate, ingest, simulate with the
    declared model, raise flags; memoised per arguments."""
    from conftest import TEST_REFINEMENT
    from fleetbrake.ingest.files import load_fleet_registry, run_ingest
    from fleetbrake.simulation.config import SimulationConfig
    from fleetbrake.simulation.predictions import (
        current_revision,
        simulate_events,
    )
    from fleetbrake.synth.generator import SynthConfig, generate_fleet
    from fleetbrake.warehouse.connection import open_warehouse

    done: dict[tuple[object, ...], Outcome] = {}
    with pytest.MonkeyPatch.context() as mp:
        # the pipeline builds its reduced models where the session keeps them
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))

        def run(*, seed: int, wagons: int, days: int, anomalies: bool) -> Outcome:
            key = (seed, wagons, days, anomalies)
            if key in done:
                return done[key]
            name = f"{'a' if anomalies else 'c'}{wagons}x{days}-s{seed}"
            out = tmp_path_factory.mktemp(name)
            seconds: dict[str, float] = {}
            began = time.perf_counter()
            config = SynthConfig(wagons=wagons, days=days, seed=seed, anomalies=anomalies)
            truth = generate_fleet(out / "fleet", config, rom=reduced_model_for)
            seconds["generate"] = time.perf_counter() - began
            began = time.perf_counter()
            run_ingest(out / "fleet", out / "fleet.duckdb", progress=False)
            seconds["ingest"] = time.perf_counter() - began
            registry = load_fleet_registry(out / "fleet")
            with open_warehouse(out / "fleet.duckdb") as wh:
                began = time.perf_counter()
                simulate_events(
                    wh,
                    registry,
                    current_revision(wh, refinement=TEST_REFINEMENT),
                    SimulationConfig(refinement=TEST_REFINEMENT),
                    progress=False,
                )
                seconds["simulate"] = time.perf_counter() - began
                began = time.perf_counter()
                report = raise_flags(wh, registry, "declared")
                seconds["flags"] = time.perf_counter() - began
                stored = wh.con.execute("SELECT flag_id FROM v_flags ORDER BY 1").fetchall()
                assert [r[0] for r in stored] == sorted(f.flag_id for f in report.flags)
                observable = {
                    id(a): _observable(wh, truth, a)  # type: ignore[arg-type]
                    for a in truth.anomalies
                }
            done[key] = Outcome(name, report.flags, truth, observable, seconds)
            return done[key]

        yield run


def _observable(wh: object, truth: object, anomaly: object) -> bool:
    """An anomaly the data can show: for a sensor fault at least a minute of ingested samples
    of its wagon within it; for a brake anomaly at least 5 minutes, outside the wagon's sensor
    faults (a loose sensor cannot see a dragging brake)."""
    query = "SELECT count(*) FROM samples WHERE wagon_id = $w AND time_utc >= $a AND time_utc < $b"
    params = {"w": anomaly.wagon_id, "a": anomaly.start_utc, "b": anomaly.end_utc}  # type: ignore[attr-defined]
    if anomaly.kind != "sensor_fault":  # type: ignore[attr-defined]
        for k, other in enumerate(truth.anomalies):  # type: ignore[attr-defined]
            if other.kind == "sensor_fault" and other.wagon_id == anomaly.wagon_id:  # type: ignore[attr-defined]
                query += f" AND NOT (time_utc >= $s{k} AND time_utc < $e{k})"
                params.update({f"s{k}": other.start_utc, f"e{k}": other.end_utc})
    ((count,),) = wh.con.execute(query, params).fetchall()  # type: ignore[attr-defined]
    return count >= (60 if anomaly.kind == "sensor_fault" else 300)  # type: ignore[attr-defined]


def _matches(flag: Flag, anomaly: object) -> bool:
    return (
        flag.wagon_id == anomaly.wagon_id  # type: ignore[attr-defined]
        and flag.kind == anomaly.kind  # type: ignore[attr-defined]
        and flag.start_utc < anomaly.end_utc  # type: ignore[attr-defined]
        and anomaly.start_utc < flag.end_utc  # type: ignore[attr-defined]
    )


def misses(outcomes: list[Outcome]) -> list[str]:
    """The false flags and the observable anomalies not found, for a failure's message."""
    out = []
    for o in outcomes:
        out += [
            f"{o.name}: false {f.flag_id}: {f.evidence}"
            for f in o.flags
            if not any(_matches(f, a) for a in o.truth.anomalies)  # type: ignore[attr-defined]
        ]
        out += [
            f"{o.name}: missed {a.wagon_id} {a.kind} {a.subtype} {a.start_utc}..{a.end_utc}"
            for a in o.truth.anomalies  # type: ignore[attr-defined]
            if o.observable[id(a)] and not any(_matches(f, a) for f in o.flags)
        ]
    return out


def score(outcomes: list[Outcome]) -> dict[str, dict[str, float]]:
    """Per kind (and ``all``): flags, true flags, anomalies, found; precision and recall."""
    table: dict[str, dict[str, float]] = {}
    for o in outcomes:
        anomalies = [a for a in o.truth.anomalies if o.observable[id(a)]]  # type: ignore[attr-defined]
        for f in o.flags:
            for kind in (f.kind, "all"):
                row = table.setdefault(
                    kind, dict.fromkeys(("flags", "true", "anomalies", "found"), 0)
                )
                row["flags"] += 1
                row["true"] += any(_matches(f, a) for a in o.truth.anomalies)  # type: ignore[attr-defined]
        for a in anomalies:
            for kind in (a.kind, "all"):
                row = table.setdefault(
                    kind, dict.fromkeys(("flags", "true", "anomalies", "found"), 0)
                )
                row["anomalies"] += 1
                row["found"] += any(_matches(f, a) for f in o.flags)
    for row in table.values():
        row["precision"] = row["true"] / row["flags"] if row["flags"] else 1.0
        row["recall"] = row["found"] / row["anomalies"] if row["anomalies"] else 1.0
    return table


NUMBER_WITH_UNIT = re.compile(r"[−-]?\d+(\.\d+)? ?(K|°C|bar|km/h|%|K/h)")


def check_evidence(flags: list[Flag]) -> None:
    for f in flags:
        assert f.wagon_id in f.evidence, f.evidence
        assert len(NUMBER_WITH_UNIT.findall(f.evidence)) >= 1, f.evidence
        assert re.search(r"\d\d:\d\d(:\d\d)? UTC", f.evidence), f.evidence
        assert f.evidence.endswith("."), f.evidence
        assert f.severity in ("info", "warning", "alarm")
    kinds = {f.kind: f.evidence for f in flags}
    if "dragging_brake" in kinds:
        assert re.search(
            r"km/h .* bar in the brake cylinder|more than predicted", kinds["dragging_brake"]
        )
    if "weak_brake" in kinds:
        assert re.search(
            r"heated only \d+ % of the predicted rise|received \d+ % less heat than declared",
            kinds["weak_brake"],
        )


def test_flags_match_the_truth_of_small_generated_fleets(run_fleet: Callable[..., Outcome]) -> None:
    """Two seeds, 3 wagons (plus an unregistered and a badly registered one) x 1 day, every
    anomaly and imperfection on: precision and recall >= 0.9 per kind."""
    outcomes = [run_fleet(seed=seed, wagons=3, days=1, anomalies=True) for seed in (1, 12)]
    table = score(outcomes)
    print({o.name: {k: round(v, 1) for k, v in o.seconds.items()} for o in outcomes})
    print(table)
    for kind in ("sensor_fault", "weak_brake", "dragging_brake", "all"):
        assert table[kind]["anomalies"] >= 2, (kind, table)
        assert table[kind]["precision"] >= 0.9, (kind, table, misses(outcomes))
        assert table[kind]["recall"] >= 0.9, (kind, table, misses(outcomes))
    assert "overheating" not in table
    for o in outcomes:
        check_evidence(o.flags)


def test_no_brake_or_sensor_flags_on_a_clean_fleet(run_fleet: Callable[..., Outcome]) -> None:
    """Anomalies off, every imperfection on (gaps, frozen GPS speed, bad files, ...)."""
    outcome = run_fleet(seed=3, wagons=3, days=1, anomalies=False)
    wrong = [f for f in outcome.flags if f.kind != "overheating"]
    assert wrong == [], [f.evidence for f in wrong]


@pytest.mark.parametrize(("seed", "wagons"), [(2, 4), (5, 4), (15, 6)])
def test_flags_match_the_truth_of_two_day_fleets(
    run_fleet: Callable[..., Outcome], seed: int, wagons: int
) -> None:
    outcome = run_fleet(seed=seed, wagons=wagons, days=2, anomalies=True)
    outcomes = [outcome]
    table = score(outcomes)
    print(outcome.name, {k: round(v, 1) for k, v in outcome.seconds.items()}, table)
    for kind in table:
        assert table[kind]["precision"] >= 0.9, (kind, table, misses(outcomes))
        assert table[kind]["recall"] >= 0.9, (kind, table, misses(outcomes))
    check_evidence(outcome.flags)


def test_no_brake_or_sensor_flags_on_a_clean_two_day_fleet(
    run_fleet: Callable[..., Outcome],
) -> None:
    outcome = run_fleet(seed=7, wagons=4, days=2, anomalies=False)
    wrong = [f for f in outcome.flags if f.kind != "overheating"]
    assert wrong == [], [f.evidence for f in wrong]
