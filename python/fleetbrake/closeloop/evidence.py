"""The close loop's first phase, residual and evidence: the events it may fit and hold out
(flagged windows, data gaps and brakings over a frozen GPS speed left out), the wagons read
once and the events cached as arrays, and the baseline's residual on the fit events: how it
relates to what the model is driven by, the sensor noise (from its second differences within
each event window) and its effective sample size (:func:`gather_evidence` -> :class:`Evidence`).
"""

from __future__ import annotations

import datetime as dt
import math
import time
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import polars as pl

from fleetbrake.closeloop.config import CloseLoopConfig
from fleetbrake.closeloop.errors import CloseLoopError
from fleetbrake.closeloop.fitdata import FitData
from fleetbrake.closeloop.stats import (
    SelectionError,
    effective_sample_size,
    noise_from_residual,
    root_mean_square,
)
from fleetbrake.closeloop.workers import Workers
from fleetbrake.flags.stats import frozen_speed_brakings
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.effects import Effect
from fleetbrake.simulation.config import SimulationConfig
from fleetbrake.simulation.predictions import (
    Revision,
    WagonData,
    current_revision,
    load_wagon,
    stored_wagons,
)
from fleetbrake.warehouse.connection import Warehouse, sql

__all__ = [
    "EventSets",
    "Evidence",
    "ResidualSummary",
    "event_sets",
    "gather_evidence",
    "load_wagons",
    "residual_summary",
    "rmse_from_predictions",
    "screen_events",
    "unknown_heat_events",
    "used_events",
]


@dataclass(frozen=True)
class ResidualSummary:
    """How the baseline's residual (measured - predicted) on the fit events relates to what the
    model is driven by: the report's ``residual``. Only ``seconds`` when there are too few
    valid seconds to analyse."""

    seconds: int
    events: int | None = None
    mean_k: float | None = None
    rmse_k: float | None = None
    mean_heating_k: float | None = None
    mean_cooling_k: float | None = None
    correlations: dict[str, float] | None = None
    """Pearson correlation of the residual with each driver (speed, pressure, heat input,
    predicted heating, ambient, time since activation)."""

    def sentence(self, noise_k: float) -> str:
        """The report's ``evidence``: the residual in one sentence."""
        if self.correlations is None:
            return "too few valid seconds in the fit events to analyse the residual"
        strongest = sorted(self.correlations.items(), key=lambda kv: -abs(kv[1]))[:3]
        parts = ", ".join(f"{name} (r = {value:+.2f})" for name, value in strongest)
        return (
            f"over {self.events} fit events ({self.seconds} s) the residual (measured - "
            f"predicted) has RMSE {self.rmse_k:.3f} K against a sensor noise of {noise_k:.3f} "
            f"K, mean {self.mean_heating_k or 0.0:+.3f} K while heating and "
            f"{self.mean_cooling_k or 0.0:+.3f} K while cooling; it correlates most with "
            f"{parts}"
        )


class EventSets(NamedTuple):
    """The events of a run, as the exclusion rule leaves them."""

    fit: pl.DataFrame
    """Unflagged events starting before the holdout date, with predictions."""
    holdout: pl.DataFrame
    """Unflagged events starting on or after it."""
    every: dict[str, list[str]]
    """``fit`` and ``holdout``: the ids of every event of each set, flagged ones included."""


@dataclass(frozen=True)
class Evidence:
    """What the close loop starts from: the baseline revision, the wagons and their events
    (read once), the fit, screening and holdout events cached as arrays, and the baseline's
    residual on the fit events with what it says (the sensor noise, the effective sample
    size, the :class:`ResidualSummary`)."""

    base: Revision
    wagons: Mapping[str, WagonConfig]
    all_events: pl.DataFrame
    """Every event with predictions (``q_closeloop_events``)."""
    loaded: Mapping[str, WagonData]
    """The samples of every wagon with events."""
    unknown_heat: frozenset[str]
    """Events braking over a frozen GPS speed (:func:`unknown_heat_events`)."""
    events: EventSets
    fit_data: FitData
    hold_data: FitData | None
    screen_data: FitData
    """The screening events' data (:func:`screen_events`; ``fit_data`` itself when they are
    every fit event)."""
    residual: np.ndarray
    """(fit_data seconds) measured - predicted by the baseline (NaN: no prediction)."""
    ok: np.ndarray
    """(fit_data seconds) where ``residual`` is finite."""
    noise_k: float
    n_eff: Mapping[str, float]
    """The baseline residual's effective sample size on ``fit`` and ``screen`` (one count per
    data set: candidates are compared on it)."""
    summary: ResidualSummary

    @property
    def present(self) -> frozenset[type[Effect]]:
        """The effect classes the baseline revision already has."""
        return frozenset(type(e) for e in self.base.effects)

    @property
    def screened_on(self) -> str:
        """``fit`` when the screening events are every fit event, else ``screen``."""
        return "fit" if self.screen_data is self.fit_data else "screen"


def gather_evidence(wh: Warehouse, config: CloseLoopConfig, workers: Workers) -> Evidence:
    """The baseline revision and its residual on the fit events: the close loop's first phase
    (the load's seconds and evaluations counted on ``workers``)."""
    clock = time.perf_counter()
    wagons = stored_wagons(wh)
    if not wagons:
        raise CloseLoopError(f"{wh.path}: no registry stored: run `fleetbrake run` first")
    # the baseline keeps the solver and mesh it was made with; a database with no revision yet
    # gets the declared one as ``run`` would make it
    base = current_revision(wh, config.simulation.solver, config.simulation.refinement)
    all_events = wh.con.sql(sql("q_closeloop_events")).pl()
    sim = config.simulation
    # each wagon read once (every wagon with events: the flags judged again may free the
    # events of one); the fit, screening and holdout events cached as arrays once
    loaded = load_wagons(wh, wagons, all_events, sim)
    unknown_heat = unknown_heat_events(loaded)
    sets = event_sets(wh, base.name, config, unknown_heat)
    fit, holdout = sets.fit, sets.holdout
    if fit.height == 0:
        raise CloseLoopError(
            f"{wh.path}: no unflagged event with predictions before {config.holdout_from}"
        )
    fit_data = FitData.build(loaded, fit, sim, base)
    hold_data = FitData.build(loaded, holdout, sim, base) if holdout.height else None
    screen = screen_events(fit, config.screen_events)
    screen_data = (
        fit_data if screen.height == fit.height else FitData.build(loaded, screen, sim, base)
    )
    workers.timing["load_s"] = time.perf_counter() - clock

    base_predicted = fit_data.predict(base.effects)
    workers.count("load", 1)
    base_frame = fit_data.frame(base.effects, base_predicted)
    summary = residual_summary(base_frame)
    r_all = fit_data.measured_c - base_predicted
    ok = np.isfinite(r_all)
    r_base = r_all[ok]
    noise_k = _sensor_noise(r_base, fit_data, ok, base_frame)
    # one effective sample size per data set, the baseline's: the residual of a missing
    # effect is the most correlated, and candidates are compared on one count
    n_eff = {"fit": effective_sample_size(r_base, fit_data.blocks[ok])}
    if screen_data is fit_data:
        n_eff["screen"] = n_eff["fit"]
    else:
        r_screen = screen_data.residual(base.effects)
        workers.count("load", 1)
        keep = np.isfinite(r_screen)
        n_eff["screen"] = effective_sample_size(r_screen[keep], screen_data.blocks[keep])
    return Evidence(
        base=base,
        wagons=wagons,
        all_events=all_events,
        loaded=loaded,
        unknown_heat=unknown_heat,
        events=sets,
        fit_data=fit_data,
        hold_data=hold_data,
        screen_data=screen_data,
        residual=r_all,
        ok=ok,
        noise_k=noise_k,
        n_eff=n_eff,
        summary=summary,
    )


def residual_summary(frame: pl.DataFrame) -> ResidualSummary:
    """How the residual relates to what the model is driven by (fit events)."""
    f = (
        frame.filter(pl.col("measured_sensor_c").is_not_null())
        .with_columns(r=pl.col("measured_sensor_c") - pl.col("predicted_sensor_c"))
        .with_columns(
            rise=pl.col("predicted_sensor_c")
            - pl.col("predicted_sensor_c").first().over("event_id"),
            since_s=(
                pl.col("time_utc") - pl.col("time_utc").first().over("event_id")
            ).dt.total_seconds(),
        )
    )
    if f.height < 10:
        return ResidualSummary(f.height)
    r = f["r"].to_numpy()
    means: dict[str, float | None] = {}
    for phase in ("heating", "cooling"):
        part = f.filter(pl.col("phase") == phase)["r"].to_numpy()
        means[phase] = float(part.mean()) if part.size else None
    correlations = {}
    for name, col in [
        ("speed", "speed_kmh"),
        ("pressure", "brake_pressure_bar"),
        ("heat input", "flux_w_m2"),
        ("predicted heating", "rise"),
        ("ambient", "ambient_c"),
        ("time since activation", "since_s"),
    ]:
        x = f[col].to_numpy().astype(np.float64)
        ok = np.isfinite(x)
        if ok.sum() > 10 and np.std(x[ok]) > 0:
            correlations[name] = float(np.corrcoef(x[ok], r[ok])[0, 1])
    return ResidualSummary(
        seconds=f.height,
        events=f["event_id"].n_unique(),
        mean_k=float(r.mean()),
        rmse_k=root_mean_square(r),
        mean_heating_k=means["heating"],
        mean_cooling_k=means["cooling"],
        correlations=correlations,
    )


def _noise_from_first_differences(frame: pl.DataFrame) -> float:
    """Sensor noise from the residual's second-to-second changes within each event."""
    diffs = (
        frame.with_columns(r=pl.col("measured_sensor_c") - pl.col("predicted_sensor_c"))
        .with_columns(d=pl.col("r").diff().over("event_id"))
        .get_column("d")
        .drop_nulls()
        .drop_nans()
        .to_numpy()
    )
    return float(np.std(diffs) / math.sqrt(2.0)) if diffs.size > 10 else float("nan")


def _sensor_noise(r: np.ndarray, data: FitData, ok: np.ndarray, frame: pl.DataFrame) -> float:
    """The sensor noise from the residual's second differences within each event window
    (:func:`~fleetbrake.closeloop.stats.noise_from_residual`); from its first differences
    when too few seconds for that."""
    seconds = (data.time_utc[ok] - data.time_utc[ok].min()).astype("timedelta64[us]")
    try:
        return noise_from_residual(r, data.event[ok], seconds.astype(np.float64) / 1e6)
    except SelectionError:
        return _noise_from_first_differences(frame)


def used_events(wh: Warehouse, revision: str, settle_after_flag_s: float) -> pl.DataFrame:
    """Events with predictions of ``revision``; column ``flagged``: whether the window
    overlaps a disturbance of its wagon or starts within ``settle_after_flag_s`` after one.
    Disturbances: the anomaly flags, and the windows of events cut by a data gap
    (``complete`` false: part of their heat input was never logged)."""
    return wh.con.sql(
        sql("q_closeloop_used_events"),
        params={"revision": revision, "settle_us": round(settle_after_flag_s * 1e6)},
    ).pl()


def event_sets(
    wh: Warehouse,
    revision: str,
    config: CloseLoopConfig,
    unknown_heat: Collection[str] = frozenset(),
) -> EventSets:
    """The fit and holdout events the exclusion rule leaves (flags as they stand now, less
    the ``unknown_heat`` events: :func:`unknown_heat_events`), and the ids of every event of
    each set."""
    every = used_events(wh, revision, config.settle_after_flag_s)
    cutoff = dt.datetime.combine(config.holdout_from, dt.time())
    before = pl.col("start_utc") < cutoff
    sets_all = {
        "fit": every.filter(before)["event_id"].to_list(),
        "holdout": every.filter(~before)["event_id"].to_list(),
    }
    used = every.filter(~pl.col("flagged") & ~pl.col("event_id").is_in(list(unknown_heat)))
    return EventSets(used.filter(before), used.filter(~before), sets_all)


def unknown_heat_events(loaded: Mapping[str, WagonData]) -> frozenset[str]:
    """Events braking over a frozen GPS speed (``flags.stats.frozen_speed_brakings``, the
    rule by which the flags call a block unsure): the logged speed is not the wagon's, so
    the heat input the model is given is not the one the block got (one such braking of a
    generated fleet left 17-30 K of residual and decided an adequacy verdict alone)."""
    out: set[str] = set()
    for data in loaded.values():
        for series in data.spans:
            frozen = frozen_speed_brakings(series)
            if not frozen:
                continue
            for event_id, a, b, _complete in series.events:
                if any(first <= b and last > a for first, last in frozen):
                    out.add(event_id)
    return frozenset(out)


def rmse_from_predictions(wh: Warehouse, revision: str, event_ids: Sequence[str]) -> float:
    """RMSE over every second of these events' windows with a valid measurement."""
    ((value,),) = wh.con.execute(
        sql("q_closeloop_rmse"), {"revision": revision, "event_ids": [str(e) for e in event_ids]}
    ).fetchall()
    return float(value) if value is not None else float("nan")


def screen_events(fit: pl.DataFrame, count: int) -> pl.DataFrame:
    """The screening subset: the earliest fit events of each wagon, taken in turn across the
    wagons (its first, then its second, ...) up to ``count`` events. Each wagon's chain is
    simulated only up to its last chosen window: early events keep the chains short."""
    if fit.height <= count:
        return fit
    ranked = fit.with_columns(_rank=pl.col("start_utc").rank("ordinal").over("wagon_id")).sort(
        "_rank", "start_utc"
    )
    return ranked.head(count).drop("_rank").sort("wagon_id", "start_utc")


def load_wagons(
    wh: Warehouse,
    wagons: Mapping[str, WagonConfig],
    events: pl.DataFrame,
    sim: SimulationConfig,
    have: Mapping[str, WagonData] | None = None,
) -> dict[str, WagonData]:
    """The samples and events of the wagons of ``events`` (those not in ``have``), each
    read once."""
    out: dict[str, WagonData] = {}
    for wagon_id in events["wagon_id"].unique(maintain_order=True).to_list():
        wagon = wagons.get(wagon_id)
        if wagon is not None and wagon_id not in (have or {}):
            out[wagon_id] = load_wagon(wh, wagon, sim)
    return out
