"""The ``fleetbrake`` command line: parses arguments, calls one job, maps
:class:`fleetbrake.errors.FleetbrakeError` to its message and exit code once."""
