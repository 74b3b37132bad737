"""``fleetbrake watch``: the always-on service that takes every log file landing complete in
``FLEET_DIR/logs/`` through exactly what ``fleetbrake run`` does (``docs/operations.md``).

* :mod:`.landing`: which files under ``logs/`` are complete (renamed into place, closed after
  writing, or unchanged for ``settle_s``) and which are still being written;
* :mod:`.service`: the observer, the rescans against the ingestion ledger, the units of work
  (one :func:`fleetbrake.app.run.run_fleet` each, the database held only meanwhile), the
  health line and the outcome of each processed file;
* :mod:`.faults`: why a unit failed, as the one sentence the service logs for it;
* :mod:`fleetbrake.cli.watch`: the ``watch`` command, its signals and its ``--json`` lines.
"""
