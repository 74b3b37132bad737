"""The estimation stage of ``fleetbrake run`` and ``close-loop``: the virtual sensor's contact
temperature at every logged second of every wagon (``v_contact_estimates``, interface v2).

::

    from fleetbrake.simulation.estimates import estimate_wagons, wagon_estimates

    report = estimate_wagons(wh, registry, rev, engine=engine)   # what changed, re-estimated
    frame = wagon_estimates(wh, "SGG-0001", rev.name)            # one wagon's rows, polars

Per span of a wagon's data (:mod:`fleetbrake.ingest.spans`: a stretch without a gap
longer than 6 h), with :mod:`fleetbrake.model.estimator` (a Kalman filter and
Rauch-Tung-Striebel smoother on the reduced model's state, augmented with the unexplained
friction-face heat power; ``docs/estimator.md``), over every logged second of the span as one
series, from the prior at its first reading (as the simulation starts each span): the
declared inputs are the simulation's (the same 1 Hz grid, the speed's running median of
:class:`~fleetbrake.simulation.chains.ChainParams`), the revision's effects applied; missing,
faulty and frozen readings (:func:`frozen_readings`) skip the update; an unlogged interval
longer than ``max_interpolated_gap_s`` is a standstill
(:mod:`~fleetbrake.simulation.estimates.wagon`).

Stored (``warehouse/sql/schema_estimates.sql``, ``schema_pipeline.sql``;
:mod:`~fleetbrake.simulation.estimates.rows`, :mod:`~fleetbrake.simulation.estimates.spans`):

* ``contact_estimates`` (behind ``v_contact_estimates``): one row per wagon, logged second and
  revision, the filtered and smoothed estimates with their 95 % bounds, the innovation, and
  for the flags and recordings the smoothed maximum and power and the innovation's sd;
* ``estimated_spans``: the keys each span was estimated from, and the noise it was estimated
  with. A span whose data (``spans.data_key``), registry entry, revision, the revision's σ_w
  and configuration are unchanged is not estimated again (a second ``run`` adds nothing); a
  late file re-estimates its span only, whose rows are replaced whole in one transaction
  (several spans per transaction, never splitting one); the rows of a span that no longer
  exists are deleted;
* ``estimator_noise``: a revision's σ_w fitted by maximum likelihood on the innovations of
  the close loop's fit days (:func:`fit_revision_noise`, called by the close loop when it
  makes a revision).

The noise (``docs/estimator.md``; :mod:`~fleetbrake.simulation.estimates.noise`): a span's
results are a function of its own data and the revision only. σ_v is the **span's**, from its
own readings (:func:`wagon_noise`: the median absolute deviation of their second
differences; ``docs/decisions/0009-spans.md``); σ_w is the **revision's**: fitted when the
close loop makes it, else the documented default ``EstimationConfig.power_noise_w_per_sqrt_s``.
``EstimationConfig.noise`` gives both instead (method ``given``).

The span is the unit of work (:mod:`~fleetbrake.simulation.estimates.stage`): the parent
reads a chunk of spans' samples as Arrow with one query, their time ranges only
(:func:`estimation_chunk`, about ``EstimationConfig.chunk_rows`` samples; :func:`estimate_task`
reads one span's, the same table), :func:`estimate_chunk` cuts it into the spans' tasks and
:func:`estimate_wagon` (pure, picklable, no database) estimates each and returns its rows as
Arrow; the parent, the single writer, commits them in bulk, several whole spans per
transaction (``EstimationConfig.batch_rows``), on a writer thread while it reads and hands out
the next chunks (the simulation's pipeline, :func:`~fleetbrake.simulation.store.chunk_pipeline`).
``engine``: the builtin ``map`` by default, an engine's workers otherwise; the rows are the
same either way. :func:`fit_revision_noise` fits its wagons on the engine the same way
(:func:`fit_wagon_noise`, one partition a wagon).
"""

from __future__ import annotations

from fleetbrake.simulation.estimates.config import (
    DEFAULT_POWER_NOISE_W_PER_SQRT_S,
    EstimationConfig,
)
from fleetbrake.simulation.estimates.noise import (
    NoiseFitTask,
    WagonNoiseFit,
    fit_revision_noise,
    fit_wagon_noise,
    revision_power_noise,
)
from fleetbrake.simulation.estimates.rows import ESTIMATE_SCHEMA, estimate_rows
from fleetbrake.simulation.estimates.spans import forget_span_estimates, replace_span_estimates
from fleetbrake.simulation.estimates.stage import EstimationReport, estimate_wagons
from fleetbrake.simulation.estimates.store import (
    EstimatedSpan,
    StoredNoise,
    estimate_task,
    estimated_spans,
    estimation_chunk,
    replace_estimates,
    stored_noise,
    wagon_estimates,
)
from fleetbrake.simulation.estimates.wagon import (
    EstimateChunk,
    EstimateResult,
    EstimateTask,
    chunk_tasks,
    estimate_chunk,
    estimate_wagon,
    estimator_series,
    frozen_readings,
    reading_noise_k,
    wagon_noise,
)

__all__ = [
    "DEFAULT_POWER_NOISE_W_PER_SQRT_S",
    "ESTIMATE_SCHEMA",
    "EstimateChunk",
    "EstimateResult",
    "EstimateTask",
    "EstimatedSpan",
    "EstimationConfig",
    "EstimationReport",
    "NoiseFitTask",
    "StoredNoise",
    "WagonNoiseFit",
    "chunk_tasks",
    "estimate_chunk",
    "estimate_rows",
    "estimate_task",
    "estimate_wagon",
    "estimate_wagons",
    "estimated_spans",
    "estimation_chunk",
    "estimator_series",
    "fit_revision_noise",
    "fit_wagon_noise",
    "forget_span_estimates",
    "frozen_readings",
    "reading_noise_k",
    "replace_estimates",
    "replace_span_estimates",
    "revision_power_noise",
    "stored_noise",
    "wagon_estimates",
    "wagon_noise",
]
