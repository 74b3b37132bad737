"""The estimation stage of ``fleetbrake run`` and ``close-loop``: the virtual sensor's contact
temperature at every logged second of every wagon (``v_contact_estimates``, interface v2).

::

    from fleetbrake.simulation.estimates import estimate_wagons, wagon_estimates

    report = estimate_wagons(wh, registry, rev, engine=engine)   # what changed, re-estimated
    frame = wagon_estimates(wh, "SGG-0001", rev.name)            # one wagon's rows, polars

Per wagon, with :mod:`fleetbrake.model.estimator` (a Kalman filter and Rauch-Tung-Striebel
smoother on the reduced model's state, augmented with the unexplained friction-face heat
power; ``docs/estimator.md``), over every logged second of the wagon's whole data as one
series: the declared inputs are the simulation's (the same 1 Hz grid, the speed's running
median of :class:`~fleetbrake.simulation.chains.ChainParams`), the revision's effects
applied; missing, faulty and frozen readings (:func:`frozen_readings`) skip the update; an
unlogged interval longer than ``max_interpolated_gap_s`` is a standstill
(:mod:`~fleetbrake.simulation.estimates.wagon`).

Stored (``warehouse/sql/schema_estimates.sql``; :mod:`~fleetbrake.simulation.estimates.rows`,
:mod:`~fleetbrake.simulation.estimates.store`):

* ``contact_estimates`` (behind ``v_contact_estimates``): one row per wagon, logged second and
  revision, the filtered and smoothed estimates with their 95 % bounds, the innovation, and
  for the flags and recordings the smoothed maximum and power and the innovation's sd;
* ``estimated_wagons``: the keys each wagon was estimated from, and the noise it was
  estimated with. A wagon whose data (its files and samples: ``q_estimates_wagon_data.sql``),
  registry entry, revision, the revision's σ_w and configuration are unchanged is not
  estimated again (a second ``run`` adds nothing); a late file re-estimates its wagon only,
  whose rows are replaced whole in one transaction (several wagons per transaction, never
  splitting one);
* ``estimator_noise``: a revision's σ_w fitted by maximum likelihood on the innovations of
  the close loop's fit days (:func:`fit_revision_noise`, called by the close loop when it
  makes a revision).

The noise (``docs/estimator.md``; :mod:`~fleetbrake.simulation.estimates.noise`): a wagon's results are a function of its own data and the
revision only. σ_v is the **wagon's**, from its own readings (:func:`wagon_noise`: the median
absolute deviation of their second differences); σ_w is the **revision's**: fitted when the
close loop makes it, else the documented default ``EstimationConfig.power_noise_w_per_sqrt_s``.
``EstimationConfig.noise`` gives both instead (method ``given``).

The wagon is the unit of work (:mod:`~fleetbrake.simulation.estimates.stage`): the parent
reads a chunk of whole wagons' samples as Arrow with one query (:func:`estimation_chunk`,
about ``EstimationConfig.chunk_rows`` samples; :func:`estimate_task` reads one wagon's, the
same table), :func:`estimate_chunk` cuts it into the wagons' tasks and :func:`estimate_wagon` (pure, picklable, no database) estimates each
and returns its rows as Arrow; the parent, the single writer, commits them in bulk, several
whole wagons per transaction (``EstimationConfig.batch_rows``), on a writer thread while it
reads and hands out the next chunks (the simulation's pipeline,
:func:`~fleetbrake.simulation.store.chunk_pipeline`).
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
from fleetbrake.simulation.estimates.stage import EstimationReport, estimate_wagons
from fleetbrake.simulation.estimates.store import (
    EstimatedWagon,
    StoredNoise,
    estimate_task,
    estimated_wagon_ids,
    estimated_wagons,
    estimation_chunk,
    estimation_data_keys,
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
    "EstimatedWagon",
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
    "estimated_wagon_ids",
    "estimated_wagons",
    "estimation_chunk",
    "estimation_data_keys",
    "estimator_series",
    "fit_revision_noise",
    "fit_wagon_noise",
    "frozen_readings",
    "reading_noise_k",
    "replace_estimates",
    "revision_power_noise",
    "stored_noise",
    "wagon_estimates",
    "wagon_noise",
]
