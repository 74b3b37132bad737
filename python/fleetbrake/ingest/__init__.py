"""Files -> warehouse: the ingestion ledger, parsing, quarantine, samples, and the braking
events detected in them.

One module per idea: :mod:`~fleetbrake.ingest.config` (the settings), :mod:`~fleetbrake.ingest.scan`
(the log files of a fleet directory), :mod:`~fleetbrake.ingest.reading` (one file's bytes parsed
into samples), :mod:`~fleetbrake.ingest.validation` (the per-row checks and their repairs),
:mod:`~fleetbrake.ingest.quarantine` (why a file is refused), :mod:`~fleetbrake.ingest.prepare`
(the workers' partitions of files, each read, hashed and judged),
:mod:`~fleetbrake.ingest.ledger` (what the warehouse holds of each file, and the batches that
write new ones), :mod:`~fleetbrake.ingest.files` (the ingestion of a fleet directory:
:func:`~fleetbrake.ingest.files.ingest_fleet`, ``fleetbrake ingest``),
:mod:`~fleetbrake.ingest.detection` (the braking events of one wagon's samples) and
:mod:`~fleetbrake.ingest.events` (the ``events`` table kept up to date after an ingestion).
"""
