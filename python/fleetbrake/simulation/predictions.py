"""``fleetbrake run``: ingest what is new, detect events, simulate every new event with the
current model revision, raise flags (contract: ``shared/spec/interface.md``).

Simulation of the events of one wagon, per contiguous *chain* of data (seconds with gaps of
at most ``max_gap_s`` filled by interpolation; a longer gap starts a new chain):

* ``initial_state="carried"`` (default): the block is simulated continuously through the
  chain from a uniform start at its first valid reading, so at each activation it holds the
  non-uniform field the previous brakings left. At each activation the field is shifted
  uniformly by the mean of measured - predicted over the ``anchor_s`` seconds before it
  (re-anchoring: exact in the reduced model's ``T = T_ref + θ`` form; it removes what has
  accumulated since, so a prediction is never further from the data than one event's worth
  of model error, and averaging keeps the sensor noise out of the anchor).
* ``initial_state="uniform"``: the paper's way: each event from a uniform block at the
  temperature measured at activation.

Each event's window runs from activation until ``after_release_s`` after release, the next
event's activation, or the end of the chain, whichever is first. ``docs/pipeline.md`` gives
the measured comparison of the two initialisations.
"""

from __future__ import annotations

import datetime as dt
import json
import os
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np
import polars as pl

from fleetbrake.fleet.registry import Registry, WagonConfig
from fleetbrake.model.effects import EffectSet
from fleetbrake.model.rom import FullModelRunner, ReducedModel
from fleetbrake.model.timeline import simulate_timeline
from fleetbrake.warehouse.connection import Warehouse

__all__ = [
    "DECLARED",
    "Revision",
    "SimulationConfig",
    "SimulationReport",
    "chains",
    "current_revision",
    "ensure_declared",
    "simulate_events",
    "store_registry",
    "stored_wagons",
    "wagon_samples",
]

DECLARED = "declared"


@dataclass(frozen=True)
class Revision:
    """A model revision: its name and the effects it adds to the declared model."""

    name: str
    effects: EffectSet = field(default_factory=EffectSet)
    solver: str = "rom"


@dataclass(frozen=True)
class SimulationConfig:
    after_release_s: int = 600
    initial_state: Literal["carried", "uniform"] = "carried"
    max_gap_s: int = 10
    """Gaps in the data up to this long are interpolated; a longer one ends a chain."""
    anchor_s: int = 30
    """Carried state: the field is shifted by the mean of measured - predicted over this many
    seconds up to activation (one reading would add its noise to every prediction)."""
    refinement: float | None = None
    """Mesh refinement of the models (None: ``$FLEETBRAKE_REFINEMENT`` or 1.0)."""
    solver: Literal["rom", "full"] = "rom"
    """What a new ``declared`` revision predicts with: the reduced model (default), or the
    full finite-element model (the reference; a thousand times slower). A revision keeps the
    solver it was made with."""


@dataclass
class SimulationReport:
    events_simulated: int = 0
    prediction_rows: int = 0
    skipped: list[str] = field(default_factory=list)
    """Events not simulated, each with the reason (naming the event)."""


def _utc_now() -> dt.datetime:
    return dt.datetime.now(dt.UTC).replace(tzinfo=None)


def ensure_declared(wh: Warehouse, solver: str = "rom") -> None:
    """Record the declared model's revision (the current one) if the warehouse has none."""
    ((count,),) = wh.con.execute("SELECT count(*) FROM model_revisions").fetchall()
    if count == 0:
        wh.con.execute(
            "INSERT INTO model_revisions VALUES "
            "($name, NULL, NULL, $params, NULL, NULL, $solver, TRUE, $now)",
            {
                "name": DECLARED,
                "params": json.dumps({"effects": []}),
                "solver": solver,
                "now": _utc_now(),
            },
        )


def revision(wh: Warehouse, name: str) -> Revision:
    rows = wh.con.execute(
        "SELECT parameters_json, solver FROM model_revisions WHERE model_revision = $name",
        {"name": name},
    ).fetchall()
    if not rows:
        raise KeyError(f"{wh.path}: no model revision {name!r}")
    params = json.loads(rows[0][0])
    return Revision(name, EffectSet.from_list(params.get("effects", [])), rows[0][1])


def current_revision(wh: Warehouse, solver: str = "rom") -> Revision:
    ensure_declared(wh, solver)
    rows = wh.con.execute(
        "SELECT model_revision FROM model_revisions WHERE is_current "
        "ORDER BY created_utc DESC LIMIT 1"
    ).fetchall()
    return revision(wh, rows[0][0] if rows else DECLARED)


def store_registry(wh: Warehouse, registry: Registry) -> None:
    """Keep the registry entries ``run`` used, for commands given only the database."""
    rows = pl.DataFrame(
        {
            "wagon_id": list(registry.wagons),
            "config_json": [json.dumps(asdict(w)) for w in registry.wagons.values()],
            "source": str(registry.path),
            "updated_utc": _utc_now(),
        },
        schema_overrides={"updated_utc": pl.Datetime("us")},
    )
    wh.con.execute("BEGIN TRANSACTION")
    try:
        wh.con.register("fb_registry", rows)
        wh.con.execute(
            "DELETE FROM wagon_registry WHERE wagon_id IN (SELECT wagon_id FROM fb_registry)"
        )
        wh.con.execute("INSERT INTO wagon_registry SELECT * FROM fb_registry")
        wh.con.unregister("fb_registry")
        wh.con.execute("COMMIT")
    except BaseException:
        wh.con.execute("ROLLBACK")
        raise


def stored_wagons(wh: Warehouse) -> dict[str, WagonConfig]:
    """The registry entries the last ``run`` stored (checked again on the way in)."""
    rows = wh.con.execute("SELECT wagon_id, config_json FROM wagon_registry").fetchall()
    return {wagon_id: WagonConfig(**json.loads(text)) for wagon_id, text in rows}


def _pending_events(wh: Warehouse, rev: str, event_ids: Iterable[str] | None) -> pl.DataFrame:
    events = wh.con.sql(
        "SELECT e.event_id, e.wagon_id, e.start_utc, e.end_utc, e.detected_utc "
        "FROM events e ORDER BY e.wagon_id, e.start_utc"
    ).pl()
    done = wh.con.sql(
        "SELECT event_id, detected_utc FROM simulated_events WHERE model_revision = $rev",
        params={"rev": rev},
    ).pl()
    if event_ids is not None:
        wanted = pl.Series(list(event_ids), dtype=pl.String)
        events = events.filter(pl.col("event_id").is_in(wanted.implode()))
    elif done.height:
        events = events.join(done, on=["event_id", "detected_utc"], how="anti")
    return events


def wagon_samples(
    wh: Warehouse, wagon_id: str, from_utc: dt.datetime, to_utc: dt.datetime
) -> pl.DataFrame:
    return wh.con.sql(
        "SELECT time_utc, speed_kmh, brake_pressure_bar, block_temp_c, ambient_temp_c "
        "FROM samples WHERE wagon_id = $wagon AND time_utc BETWEEN $t0 AND $t1 "
        "ORDER BY time_utc",
        params={"wagon": wagon_id, "t0": from_utc, "t1": to_utc},
    ).pl()


def chains(samples: pl.DataFrame, max_gap_s: int) -> list[pl.DataFrame]:
    """Contiguous 1 Hz chains: gaps up to ``max_gap_s`` interpolated (the measured temperature
    stays missing there), a longer gap starts a new chain."""
    if samples.height == 0:
        return []
    samples = samples.unique("time_utc", keep="first").sort("time_utc")
    gap = samples["time_utc"].diff().dt.total_seconds().fill_null(0)
    chain_id = (gap > max_gap_s).cum_sum()
    chains = []
    for part in samples.with_columns(chain=chain_id).partition_by("chain", maintain_order=True):
        grid = pl.DataFrame(
            {
                "time_utc": pl.datetime_range(
                    part["time_utc"][0], part["time_utc"][-1], "1s", eager=True, time_unit="us"
                )
            }
        )
        joined = grid.join(
            part.drop("chain").with_columns(pl.col("time_utc").dt.cast_time_unit("us")),
            on="time_utc",
            how="left",
        )
        filled = joined.with_columns(
            pl.col("speed_kmh").interpolate().fill_null(strategy="forward").fill_null(0.0),
            pl.col("brake_pressure_bar")
            .interpolate()
            .fill_null(strategy="forward")
            .fill_null(0.0)
            .clip(lower_bound=0.0),
            pl.col("ambient_temp_c").interpolate().fill_null(strategy="forward"),
        ).with_columns(pl.col("ambient_temp_c").fill_null(strategy="backward"))
        chains.append(filled)
    return chains


def _ambient(chain: pl.DataFrame, wagon: WagonConfig) -> np.ndarray:
    amb = chain["ambient_temp_c"].to_numpy().astype(np.float64)
    return np.where(np.isfinite(amb), amb, wagon.ambient_temp_c)


def _measured_at(measured: np.ndarray, k: int, window_s: int = 3) -> float | None:
    """The measured sensor at sample k, or the nearest valid reading within ``window_s``."""
    for d in range(window_s + 1):
        for j in (k - d, k + d):
            if 0 <= j < measured.size and np.isfinite(measured[j]):
                return float(measured[j])
    return None


def simulate_events(
    wh: Warehouse,
    registry: Registry | Mapping[str, WagonConfig],
    rev: Revision,
    config: SimulationConfig | None = None,
    *,
    event_ids: Iterable[str] | None = None,
    progress: bool | None = None,
) -> SimulationReport:
    """Simulate the events not yet simulated with ``rev`` (or ``event_ids``) into
    ``predictions``; each wagon in one transaction."""
    config = config or SimulationConfig()
    wagons_by_id = registry.wagons if isinstance(registry, Registry) else registry
    report = SimulationReport()
    pending = _pending_events(wh, rev.name, event_ids)
    if pending.height == 0:
        return report
    all_events = wh.con.sql(
        "SELECT event_id, wagon_id, start_utc, end_utc FROM events ORDER BY wagon_id, start_utc"
    ).pl()
    wagons = pending["wagon_id"].unique(maintain_order=True).to_list()
    show = progress if progress is not None else os.isatty(1)
    from rich.progress import Progress

    with Progress(disable=not show, transient=True) as bar:
        task = bar.add_task("simulating events", total=pending.height)
        for wagon_id in wagons:
            todo = pending.filter(pl.col("wagon_id") == wagon_id)
            wagon = wagons_by_id.get(wagon_id)
            if wagon is None:
                report.skipped += [
                    f"event {e}: wagon {wagon_id} has no valid registry entry"
                    for e in todo["event_id"]
                ]
                bar.advance(task, todo.height)
                continue
            rom = model_for(wagon, rev.solver, config.refinement)
            events = all_events.filter(pl.col("wagon_id") == wagon_id)
            frames = _simulate_wagon(wh, wagon, rom, rev, events, todo, config, report)
            _store(wh, rev, todo, frames, report)
            bar.advance(task, todo.height)
    return report


def _simulate_wagon(
    wh: Warehouse,
    wagon: WagonConfig,
    rom: ReducedModel,
    rev: Revision,
    events: pl.DataFrame,
    todo: pl.DataFrame,
    config: SimulationConfig,
    report: SimulationReport,
    wagon_chains: list[pl.DataFrame] | None = None,
) -> list[pl.DataFrame]:
    wanted = set(todo["event_id"].to_list())
    if wagon_chains is None:
        wagon_chains = load_chains(wh, wagon.wagon_id, todo, config)
    frames: list[pl.DataFrame] = []
    for chain in wagon_chains:
        t_chain = chain["time_utc"]
        inside = events.filter(
            (pl.col("start_utc") >= t_chain[0]) & (pl.col("start_utc") <= t_chain[-1])
        )
        if not set(inside["event_id"].to_list()) & wanted:
            continue
        frames += _simulate_chain(wagon, rom, rev, chain, inside, wanted, config, report)
    missing = wanted - {f["event_id"][0] for f in frames if f.height}
    report.skipped += [
        f"event {e}: no contiguous samples at its activation" for e in sorted(missing)
    ]
    return frames


def model_for(
    wagon: WagonConfig, solver: str, refinement: float | None
) -> ReducedModel | FullModelRunner:
    """The model a revision predicts with: the wagon's reduced model, or the full one."""
    if solver == "full":
        return FullModelRunner.for_wagon(wagon, refinement=refinement)
    return ReducedModel.for_wagon(wagon, refinement=refinement)


def load_chains(
    wh: Warehouse, wagon_id: str, events: pl.DataFrame, config: SimulationConfig
) -> list[pl.DataFrame]:
    """The wagon's chains of data around ``events`` (back to the start of the chain holding
    the first of them, for the carried state)."""
    span0 = events["start_utc"].min()
    span1 = events["end_utc"].max() + dt.timedelta(seconds=config.after_release_s)
    lookback = dt.timedelta(hours=12) if config.initial_state == "carried" else dt.timedelta(0)
    return chains(wagon_samples(wh, wagon_id, span0 - lookback, span1), config.max_gap_s)


def _simulate_chain(
    wagon: WagonConfig,
    rom: ReducedModel,
    rev: Revision,
    chain: pl.DataFrame,
    events: pl.DataFrame,
    wanted: set[str],
    config: SimulationConfig,
    report: SimulationReport,
) -> list[pl.DataFrame]:
    t0 = chain["time_utc"][0]
    seconds = (chain["time_utc"] - t0).dt.total_seconds().to_numpy().astype(np.int64)
    pressure = chain["brake_pressure_bar"].to_numpy().astype(np.float64)
    speed = chain["speed_kmh"].to_numpy().astype(np.float64)
    ambient = _ambient(chain, wagon)
    measured = chain["block_temp_c"].to_numpy().astype(np.float64)
    n = seconds.size
    starts = [int((s - t0).total_seconds()) for s in events["start_utc"]]
    ends = [int((s - t0).total_seconds()) for s in events["end_utc"]]
    ids = events["event_id"].to_list()
    frames = []
    # carried: a uniform start at the first valid reading of the chain
    first = np.flatnonzero(np.isfinite(measured))
    t_ref = float(measured[first[0]]) if first.size else float(ambient[0])
    state = None
    cursor = 0
    for i, (k0, k_end, event_id) in enumerate(zip(starts, ends, ids, strict=True)):
        k1 = min(k_end + config.after_release_s, n - 1)
        if i + 1 < len(starts):
            k1 = min(k1, starts[i + 1])
        if config.initial_state == "carried" and k0 > cursor:
            lead = simulate_timeline(
                rom,
                wagon,
                dt_s=1.0,
                p_bar=pressure[cursor : k0 + 1],
                speed_kmh=speed[cursor : k0 + 1],
                ambient_c=ambient[cursor : k0 + 1],
                initial_c=t_ref,
                initial_state=state,
                effects=rev.effects,
            )
            state = lead.final_state
            back = min(config.anchor_s, lead.sensor_c.size)
            residual = measured[k0 + 1 - back : k0 + 1] - lead.sensor_c[-back:]
            valid = residual[np.isfinite(residual)]
            offset = float(valid.mean()) if valid.size else None
        else:
            offset = None
        at_start = _measured_at(measured, k0)
        if config.initial_state == "uniform" or state is None:
            if at_start is None:
                if event_id in wanted:
                    report.skipped.append(f"event {event_id}: no valid reading at activation")
                continue
            t_ref, state = at_start, None
        elif offset is not None:
            t_ref += offset  # re-anchor: shift the field uniformly
        if k1 - k0 < 2:
            continue
        window = simulate_timeline(
            rom,
            wagon,
            dt_s=1.0,
            p_bar=pressure[k0 : k1 + 1],
            speed_kmh=speed[k0 : k1 + 1],
            ambient_c=ambient[k0 : k1 + 1],
            initial_c=t_ref,
            initial_state=state,
            effects=rev.effects,
        )
        if config.initial_state == "carried":
            state, cursor = window.final_state, k1
        if event_id not in wanted:
            continue
        rows = slice(k0, k1 + 1)
        frames.append(
            pl.DataFrame(
                {
                    "event_id": event_id,
                    "wagon_id": wagon.wagon_id,
                    "time_utc": chain["time_utc"][rows],
                    "model_revision": rev.name,
                    "phase": np.where(seconds[rows] <= k_end, "heating", "cooling"),
                    "measured_sensor_c": measured[rows],
                    "predicted_sensor_c": window.sensor_c,
                    "predicted_contact_mean_c": window.contact_mean_c,
                    "predicted_contact_max_c": window.contact_max_c,
                    "speed_kmh": speed[rows],
                    "brake_pressure_bar": pressure[rows],
                    "ambient_c": ambient[rows],
                    "flux_w_m2": window.sample_flux_w_m2,
                },
                strict=False,
            ).with_columns(pl.col("measured_sensor_c").fill_nan(None))
        )
    return frames


def _store(
    wh: Warehouse,
    rev: Revision,
    todo: pl.DataFrame,
    frames: list[pl.DataFrame],
    report: SimulationReport,
) -> None:
    """Replace the predictions of these events for this revision, in one transaction."""
    ids = pl.DataFrame({"event_id": todo["event_id"], "detected_utc": todo["detected_utc"]})
    rows = pl.concat(frames) if frames else None
    con = wh.con
    con.execute("BEGIN TRANSACTION")
    try:
        con.register("fb_ids", ids)
        con.execute(
            "DELETE FROM predictions WHERE model_revision = $rev "
            "AND event_id IN (SELECT event_id FROM fb_ids)",
            {"rev": rev.name},
        )
        con.execute(
            "DELETE FROM simulated_events WHERE model_revision = $rev "
            "AND event_id IN (SELECT event_id FROM fb_ids)",
            {"rev": rev.name},
        )
        if rows is not None:
            con.register("fb_rows", rows)
            con.execute(
                "INSERT INTO predictions SELECT event_id, wagon_id, time_utc, model_revision, "
                "phase, measured_sensor_c, predicted_sensor_c, predicted_contact_mean_c, "
                "predicted_contact_max_c, speed_kmh, brake_pressure_bar, ambient_c, flux_w_m2 "
                "FROM fb_rows"
            )
            con.unregister("fb_rows")
        con.execute(
            "INSERT INTO simulated_events SELECT event_id, $rev, detected_utc, $now FROM fb_ids",
            {"rev": rev.name, "now": _utc_now()},
        )
        con.unregister("fb_ids")
        con.execute("COMMIT")
    except BaseException:
        con.execute("ROLLBACK")
        raise
    report.events_simulated += len(frames)
    report.prediction_rows += 0 if rows is None else rows.height
