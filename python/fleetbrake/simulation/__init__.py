"""Events -> predictions and timelines: each wagon's block simulated through its data by the one
chain/re-anchor algorithm (:mod:`~fleetbrake.simulation.chains`, its numbers in ``ChainParams``;
a span in one call of the reduced model's kernel: :mod:`~fleetbrake.simulation.batched`),
on the 1 Hz grid of :mod:`~fleetbrake.simulation.series`; the stage that stores, per wagon and
revision, the event windows (``v_predictions``) and the timeline the flags judge, a wagon a
partition an engine may run in a worker (:mod:`~fleetbrake.simulation.predictions`), and how it
is stored and read back (:mod:`~fleetbrake.simulation.store`)."""
