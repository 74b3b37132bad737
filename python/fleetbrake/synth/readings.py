"""What a generated wagon's unit logs: its readings, with their noise and resolution, cut
into its recording sessions (:func:`sessions_as_logged`), before anything befalls the files
(:mod:`fleetbrake.synth.corrupt`)."""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from typing import Any

import numpy as np
import polars as pl

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.synth.block import SimulatedBlock
from fleetbrake.synth.config import SynthConfig, stream
from fleetbrake.synth.corrupt import Session
from fleetbrake.synth.operation import Operation
from fleetbrake.synth.wagons import WagonPlan

__all__ = ["PRESSURE_QUANTUM_BAR", "sessions_as_logged"]


PRESSURE_QUANTUM_BAR = 0.007
"""The pressure sensor's resolution (fleet-data.md)."""


def sessions_as_logged(
    config: SynthConfig,
    plan: WagonPlan,
    wagon: WagonConfig,
    op: Operation,
    result: SimulatedBlock,
    wagon_air: np.ndarray,
    times: pl.Series,
    spans: Sequence[tuple[int, int]],
    start_utc: dt.datetime,
) -> list[Session]:
    """What the wagon's unit logged in each session (readings with their noise and
    resolution), before anything befell the files."""
    n_s = op.speed_kmh.size
    rd = stream(config.seed, "readings", plan.index)
    sensor_read = np.round(result.sensor_c + rd.normal(0.0, config.sensor_noise_k, n_s), 2)
    p_read = np.maximum(op.pressure_bar + rd.normal(0.0, config.pressure_noise_bar, n_s), 0.0)
    p_read = np.round(np.round(p_read / PRESSURE_QUANTUM_BAR) * PRESSURE_QUANTUM_BAR, 3)
    v_read = np.round(np.abs(op.speed_kmh + rd.normal(0.0, config.speed_noise_kmh, n_s)), 2)
    v_read = np.where(op.speed_kmh > 0.0, v_read, np.round(np.abs(rd.normal(0.0, 0.1, n_s)), 2))
    elev_read = np.round(op.elevation_m + rd.normal(0.0, 0.8, n_s), 1)
    lat_read = np.round(op.lat_deg + rd.normal(0.0, 2e-5, n_s), 6)
    lon_read = np.round(op.lon_deg + rd.normal(0.0, 2e-5, n_s), 6)
    air_read = np.round(wagon_air + rd.normal(0.0, 0.15, n_s), 1)
    extra_col = np.round(27.6 + rd.normal(0.0, 0.05, n_s), 2)

    odd = config.odd_columns and plan.index == min(3, config.wagons - 1) and plan.registry == "ok"
    out: list[Session] = []
    for number, (a, b) in enumerate(spans):
        columns: dict[str, Any] = {
            "time_utc": times[a:b],
            "speed_kmh": v_read[a:b],
            "distance_m": np.round(op.distance_m[a:b] - op.distance_m[a], 1),
            "elevation_m": elev_read[a:b],
            "lat_deg": lat_read[a:b],
            "lon_deg": lon_read[a:b],
            "brake_pressure_bar": p_read[a:b],
            "block_temp_c": sensor_read[a:b],
        }
        if plan.ambient_column == "values":
            columns["ambient_temp_c"] = air_read[a:b]
        elif plan.ambient_column == "empty":
            columns["ambient_temp_c"] = pl.Series([None] * (b - a), dtype=pl.Float64)
        frame = pl.DataFrame(columns)
        if odd:
            frame = frame.with_columns(pl.Series("battery_v", extra_col[a:b]))
            order = [
                "time_utc",
                "block_temp_c",
                "brake_pressure_bar",
                "speed_kmh",
                "battery_v",
                "distance_m",
                "lat_deg",
                "lon_deg",
                "elevation_m",
            ]
            order += [c for c in frame.columns if c not in order]
            frame = frame.select(order)
        out.append(
            Session(
                wagon_id=plan.wagon_id,
                wagon_index=plan.index,
                number=number,
                registered=plan.registry == "ok",
                frame=frame,
                first_utc=start_utc + dt.timedelta(seconds=a),
                last_utc=start_utc + dt.timedelta(seconds=b - 1),
                odd_columns=odd,
                ambient_c=None if plan.ambient_column == "values" else wagon.ambient_temp_c,
            )
        )
    return out
