"""Judging the spans of wagons' data and storing their flags: :func:`raise_flags`.

::

    from fleetbrake.flags import FlagConfig, load_flag_config, raise_flags

    config = load_flag_config("flags.toml")            # or FlagConfig() for the defaults
    report = raise_flags(wh, registry, "declared", config)   # every span
    report = raise_flags(wh, registry, "declared", wagons=["SGG-0002"])
    report.flags                                        # what was stored in ``flags``

The flags read what the stages before stored: the samples and events, the revision's
``timeline`` (the block re-anchored at every segment, ``fleetbrake.simulation``) and its
``predictions`` of the brakings; they never simulate. How a span is judged (each step uses
only readings the steps before found good):

1. **Sensor, from the readings alone** (:mod:`fleetbrake.flags.sensor`): out of range,
   frozen, dropping out.
2. **Sensor, against the timeline**: loose, drifting (segments right after a data gap in
   which the wagon may have braked, or after a braking over frozen GPS speed, are not judged
   for ``settle_s``).
3. **Brakes** (:mod:`fleetbrake.flags.brakes`), with the readings of steps 1 and 2 left out:
   dragging (quiet windows heating while the model cools, brakings heating far more than
   predicted), weak (brakings heating far less than predicted; consecutive ones are one flag).
4. **Overheating** (:mod:`fleetbrake.flags.overheating`): the predicted contact maximum of a
   braking over ``contact_limit_c``.
5. **The virtual sensor's opinion** (:mod:`fleetbrake.flags.estimated`, ``config.estimator``):
   the stored estimates of the revision when current (``contact_estimates``; none otherwise:
   the estimation stage is the one place a wagon is estimated); its dragging and weak brakes
   combined with step 3's into one flag per anomaly, its innovations dating the sensor faults
   of steps 1-2.

Every threshold in kelvin a model error could reach is first raised to ``residual_factor`` x
the span's residual spread for the revision (:func:`~fleetbrake.flags.wagon.wagon_residual_spread`
of its own brakings, computed in its partition; :meth:`FlagConfig.scaled`).

The unit is the span (:mod:`fleetbrake.ingest.spans`: a stretch of a wagon's data without a
gap longer than 6 h), judged alone: no detector reads beyond it
(``docs/decisions/0009-spans.md``). A span without a registry entry, or whose timeline of the
revision is missing or older than its data, is judged on its readings only (step 1; the
report's notes say so). Flags are recomputed per span (a partition,
:mod:`fleetbrake.flags.partition`: the parent reads a chunk of spans as Arrow, one query per
table, their time ranges only, :func:`~fleetbrake.flags.partition.flag_chunk`;
:func:`~fleetbrake.flags.partition.judge_chunk`, pure and picklable, cuts it into the spans'
tasks and :func:`~fleetbrake.flags.partition.judge_task` judges each alone
(:func:`~fleetbrake.flags.wagon.judge_wagon`), on an engine's workers with ``engine=``) and
the spans' rows of ``flags`` (those starting in each) replaced in one transaction
(:mod:`fleetbrake.flags.storage`), with when they were judged, from which data, with which
revision and thresholds (``flagged_spans``: :func:`~fleetbrake.flags.storage.stale_spans`,
the spans whose flags are out of date, which ``fleetbrake run`` judges); ``flag_id`` is
``<kind>-<wagon>-<start as YYYYMMDDTHHMMSS>`` (``-2``, ... if taken), so the same data give
the same ids, and a flag found again keeps its ``detected_utc``.

The modules: this one (the stage, :func:`raise_flags`), :mod:`~fleetbrake.flags.wagon` (one
span judged from its arrays), :mod:`~fleetbrake.flags.partition` (a span's and a chunk's
tables, read by the parent, judged by a worker), :mod:`~fleetbrake.flags.storage` (the
``flags`` and ``flagged_spans`` rows).
"""

from __future__ import annotations

import logging
import statistics
from collections.abc import Iterable, Iterator, Mapping

from fleetbrake.flags.config import DEFAULT_FLAG_CONFIG, FlagConfig
from fleetbrake.flags.partition import (
    FLAG_CHUNK_ROWS,
    FlagChunk,
    FlagHead,
    flag_chunk,
    judge_chunk,
)
from fleetbrake.flags.records import Flag, FlagReport
from fleetbrake.flags.storage import flagged_spans, store_flags
from fleetbrake.fleet.registry import Registry, WagonConfig
from fleetbrake.ingest.spans import Span, SpanKey, orphan_spans, stored_spans
from fleetbrake.simulation.estimates import estimated_spans
from fleetbrake.simulation.predictions import revision
from fleetbrake.simulation.store import Mapper, simulated_spans, unit_chunks
from fleetbrake.warehouse.connection import Warehouse, sql

__all__ = ["current_estimates", "raise_flags"]

logger = logging.getLogger(__name__)


def raise_flags(
    wh: Warehouse,
    registry: Registry | Mapping[str, WagonConfig],
    revision_name: str,
    config: FlagConfig = DEFAULT_FLAG_CONFIG,
    *,
    wagons: Iterable[str] | None = None,
    spans: Iterable[SpanKey] | None = None,
    engine: Mapper | None = None,
    chunk_rows: int = FLAG_CHUNK_ROWS,
) -> FlagReport:
    """Recompute the flags of the spans of ``wagons`` and of ``spans`` (default, neither
    given: every span) from their samples, events and what the simulation stored for
    ``revision_name`` (their timeline and predictions) and the estimation (their estimates),
    and replace their rows of ``flags`` (those starting in each span) in one transaction; the
    flags of spans that no longer exist are removed with them. A span without a registry
    entry, or without a current timeline of the revision, is judged on its readings only (a
    note in the report names its wagon). Raises
    :class:`fleetbrake.simulation.predictions.UnknownRevisionError` for an unknown revision.

    Each span is judged alone, from its own partition. The parent reads the partitions a
    chunk of spans at a time (about ``chunk_rows`` samples: :func:`flag_chunk`, one query
    per table, the spans' time ranges only), ``engine.map`` runs :func:`judge_chunk` on each
    chunk (default: the builtin ``map``, in this process; an engine's workers otherwise),
    and the parent stores every span's flags at the end, in bulk. The flags are the same with
    any engine and chunk size."""
    rev = revision(wh, revision_name)  # the revision must exist
    if isinstance(registry, Registry):
        wagons_by_id: Mapping[str, WagonConfig] = registry.wagons
        default_ambient_c = float(registry.defaults["ambient_temp_c"])
    else:  # the entries a run stored (simulation.predictions.stored_wagons)
        wagons_by_id = registry
        default_ambient_c = WagonConfig(wagon_id="-").ambient_temp_c
    current = stored_spans(wh)
    if wagons is not None or spans is not None:
        only, keys = set(wagons or ()), set(spans or ())
        wanted = [s for s in current if s.wagon_id in only or s.key in keys]
    else:
        wanted = current
    orphans = orphan_spans(flagged_spans(wh, revision_name), current)
    report = FlagReport(wagons=sorted({s.wagon_id for s in wanted}))
    if not wanted and not orphans:  # nothing to judge: nothing read, nothing stored
        return report
    done = simulated_spans(wh, revision_name)
    estimated = current_estimates(wh, revision_name)

    def head(span: Span) -> FlagHead:
        wagon = wagons_by_id.get(span.wagon_id)
        ambient = float(wagon.ambient_temp_c if wagon else default_ambient_c)
        simulated = done.get(span.key) if wagon is not None else None
        data_key: str | None = None
        if wagon is None:
            note: str | None = "no valid registry entry; only its readings were judged"
        elif simulated is None:
            note = (
                f"not simulated with revision {revision_name}; only its readings were "
                "judged (the flags read the simulation's timeline: run the simulation first)"
            )
        elif (simulated.data_key, simulated.end_utc) != (span.data_key, span.end_utc):
            note = (
                f"its data changed since it was simulated with revision {revision_name}; "
                "only its readings were judged (run the simulation first)"
            )
        else:
            note, data_key = None, simulated.data_key
        return FlagHead(span, ambient, note, data_key, wagon, span.key in estimated)

    def chunks() -> Iterator[FlagChunk]:
        for part in unit_chunks(wanted, lambda span: span.sample_rows, chunk_rows):
            yield flag_chunk(wh, [head(s) for s in part], revision_name, config, rev)

    outcomes = map(judge_chunk, chunks()) if engine is None else engine.map(judge_chunk, chunks())
    new: list[Flag] = []
    judged: list[tuple[Span, int]] = []
    spreads: list[float] = []
    for outcome in (one for chunk in outcomes for one in chunk):
        report.notes += [n for n in outcome.notes if n not in report.notes]
        new += outcome.flags
        judged.append((outcome.span, len(outcome.flags)))
        if outcome.residual_spread_k is not None:
            spreads.append(outcome.residual_spread_k)
    if spreads:  # for the report only: each span was judged with its own
        report.residual_spread_k = float(statistics.median(spreads))
    store_flags(wh, judged, new, revision_name, config.key(), orphans)
    report.flags = new
    logger.info("flags of %d spans judged: %d flags", len(judged), len(new))
    return report


def current_estimates(wh: Warehouse, revision_name: str) -> set[SpanKey]:
    """The spans whose stored virtual-sensor estimates of the revision are current with
    their data (none when the warehouse has no estimation tables)."""
    present = wh.con.execute(sql("q_flags_has_estimates")).fetchone()
    if present is None or int(present[0]) < 2:
        return set()
    data = {s.key: (s.data_key, s.end_utc) for s in stored_spans(wh)}
    return {
        key
        for key, stored in estimated_spans(wh, revision_name).items()
        if data.get(key) == (stored.ledger.data_key, stored.ledger.end_utc)
    }
