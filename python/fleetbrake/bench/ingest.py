"""``fleetbrake bench ingest``: how fast a gzip fleet goes into the warehouse, and in how much memory.

A synthetic fleet of ``rows`` samples (simple made-up signals; only the volume matters) is
written as gzip log files (20,000 rows each, 25 per wagon) by child processes, then ingested
by this process into a fresh database, events excluded. The figures: rows, seconds, rows per
second, the peak resident memory of this process (``resource.getrusage``; the fleet writers
are other processes, so it is the ingestion's own peak) and the peak of each quarter of the
run (flat when memory does not grow with the fleet), with the machine's CPU count and load
(other processes on the machine slow the figure down).
"""

from __future__ import annotations

import datetime as dt
import multiprocessing
import os
import resource
import shutil
import sys
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import polars as pl

from fleetbrake.bench import BenchError, require_extra
from fleetbrake.fleet.logfile import log_relpath, write_log
from fleetbrake.ingest.config import IngestConfig
from fleetbrake.ingest.files import ingest_fleet
from fleetbrake.warehouse.connection import open_warehouse

__all__ = ["bench_ingest", "make_bench_fleet"]

BENCH_START_UTC = dt.datetime(2024, 3, 1, 5, 0, 0)
"""First session of the synthetic fleet."""


def _session(wagon_index: int, session_index: int, rows: int) -> pl.DataFrame:
    """A made-up 1 Hz session: sinusoidal speed, periodic brakings, a warming block."""
    rng = np.random.default_rng([wagon_index, session_index])
    time_s = np.arange(rows, dtype=np.float64)
    speed_kmh = np.clip(
        60 + 35 * np.sin(time_s / 400 + wagon_index) + rng.normal(0, 0.5, rows), 0, 120
    )
    braking = (time_s % 600) < 45
    pressure_bar = np.where(
        braking, 1.5 + rng.normal(0, 0.01, rows), np.abs(rng.normal(0, 0.01, rows))
    )
    start_utc = BENCH_START_UTC + dt.timedelta(days=session_index, hours=wagon_index % 12)
    return pl.DataFrame(
        {
            "time_utc": pl.datetime_range(
                start_utc, start_utc + dt.timedelta(seconds=rows - 1), "1s", eager=True
            ),
            "speed_kmh": np.round(speed_kmh, 2),
            "distance_m": np.round(np.cumsum(speed_kmh / 3.6), 1),
            "elevation_m": np.round(400 + 50 * np.sin(time_s / 900), 1),
            "lat_deg": np.round(46.0 + time_s * 1e-5, 6),
            "lon_deg": np.round(8.0 + time_s * 1e-5, 6),
            "brake_pressure_bar": np.round(np.round(pressure_bar / 0.007) * 0.007, 3),
            "block_temp_c": np.round(20 + 30 * braking + rng.normal(0, 0.2, rows), 1),
            "ambient_temp_c": np.round(10 + rng.normal(0, 0.1, rows), 1),
        }
    )


def _write_wagon(
    fleet_dir: str, wagon_index: int, sessions: int, rows_per_file: int, level: int
) -> int:
    """Write one wagon's sessions; returns the rows written."""
    wagon_id = f"BENCH-{wagon_index:04d}"
    written = 0
    for session_index in range(sessions):
        frame = _session(wagon_index, session_index, rows_per_file)
        start_utc = frame["time_utc"][0]
        write_log(Path(fleet_dir) / log_relpath(wagon_id, start_utc, gzip=True), frame, level=level)
        written += frame.height
    return written


def make_bench_fleet(
    fleet_dir: Path,
    rows: int,
    *,
    rows_per_file: int = 20_000,
    files_per_wagon: int = 25,
    processes: int = 2,
    gzip_level: int = 6,
) -> int:
    """Write a synthetic gzip fleet of about ``rows`` samples (whole files); returns its rows."""
    files = max(1, round(rows / rows_per_file))
    wagons = max(1, -(-files // files_per_wagon))
    fleet_dir.mkdir(parents=True, exist_ok=True)
    (fleet_dir / "fleet.toml").write_text(
        "[defaults]\nambient_temp_c = 10.0\n\n"
        + "".join(f'[[wagon]]\nid = "BENCH-{w:04d}"\n\n' for w in range(wagons)),
        encoding="utf-8",
    )
    per_wagon = [files // wagons + (1 if w < files % wagons else 0) for w in range(wagons)]
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=processes, mp_context=context) as pool:
        jobs = [
            pool.submit(_write_wagon, str(fleet_dir), w, n, rows_per_file, gzip_level)
            for w, n in enumerate(per_wagon)
            if n
        ]
        return sum(job.result() for job in jobs)


def _peak_rss_mb() -> float:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1 << 20) if sys.platform == "darwin" else peak / 1024


class _RssSampler:
    """Samples this process's resident memory every ``every_s`` seconds, in a thread."""

    def __init__(self, every_s: float = 0.2) -> None:
        self._every_s = every_s
        self._stop = threading.Event()
        self.samples_mb: list[float] = []
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        import psutil

        process = psutil.Process()
        while not self._stop.is_set():
            self.samples_mb.append(process.memory_info().rss / 1e6)
            self._stop.wait(self._every_s)

    def __enter__(self) -> _RssSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def quarter_peaks_mb(self) -> list[float]:
        """Highest resident memory in each quarter of the run (flat: no growth)."""
        n = len(self.samples_mb)
        quarters = [
            self.samples_mb[n * q // 4 : max(n * (q + 1) // 4, n * q // 4 + 1)] for q in range(4)
        ]
        return [round(max(part), 1) if part else 0.0 for part in quarters]


def bench_ingest(
    rows: int = 2_000_000,
    *,
    workdir: Path | None = None,
    fleet_dir: Path | None = None,
    rows_per_file: int = 20_000,
    config: IngestConfig | None = None,
) -> dict[str, float | int | list[float]]:
    """Ingest a synthetic gzip fleet into a fresh database; return the figures.

    The fleet is made in a temporary directory (under ``workdir``) and removed afterwards,
    unless ``fleet_dir`` is given: then it is made there if it holds no ``fleet.toml`` yet,
    reused if it does (``rows`` is then what it holds), and kept. Needs psutil (the
    ``bench`` extra).
    """
    require_extra("bench ingest", "psutil")
    root = Path(tempfile.mkdtemp(prefix="fleetbrake-bench-", dir=workdir))
    try:
        make_s = 0.0
        if fleet_dir is None or not (fleet_dir / "fleet.toml").exists():
            fleet_dir = fleet_dir or root / "fleet"
            make_started = time.perf_counter()
            written: int | None = make_bench_fleet(fleet_dir, rows, rows_per_file=rows_per_file)
            make_s = time.perf_counter() - make_started
        else:
            written = None
        gzip_mb = sum(p.stat().st_size for p in fleet_dir.rglob("*.csv.gz")) / 1e6
        with open_warehouse(root / "bench.duckdb") as wh, _RssSampler() as rss:
            started = time.perf_counter()
            report = ingest_fleet(fleet_dir, wh, config=config, progress=False)
            seconds = time.perf_counter() - started
            ((stored,),) = wh.con.execute("SELECT count(*) FROM samples").fetchall()
        if (written is not None and stored != written) or report.quarantined:
            raise BenchError(
                f"bench ingest: wrote {written} rows, stored {stored}, "
                f"{len(report.quarantined)} files quarantined"
            )
        return {
            "rows": int(stored),
            "files": len(report.ingested),
            "gzip_mb": round(gzip_mb, 1),
            "make_fleet_s": round(make_s, 1),
            "seconds": round(seconds, 3),
            "rows_per_s": round(stored / seconds),
            "peak_rss_mb": round(_peak_rss_mb(), 1),
            "rss_mb_quarter_peaks": rss.quarter_peaks_mb(),
            "cpus": os.cpu_count() or 0,
            "load_avg_1min": round(os.getloadavg()[0], 2),
            "db_mb": round((root / "bench.duckdb").stat().st_size / 1e6, 1),
        }
    finally:
        shutil.rmtree(root, ignore_errors=True)
