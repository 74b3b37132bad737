"""Bridges that land data from other transports as log files of the fleet format.

``fleetbrake bridge mqtt --broker URL --topic PATTERN --landing FLEET_DIR`` (contract:
``shared/spec/interface.md``) receives samples over MQTT and writes them as log files of
``shared/spec/fleet-data.md`` into the landing folder, where ``run`` and ``watch`` take them.
A message is acknowledged only once the file holding its samples is durably written, and a
sample lands in one file only, however often it is delivered. The pieces:

* :mod:`fleetbrake.bridge.config`: the settings (:class:`BridgeConfig`);
* :mod:`fleetbrake.bridge.payload`: the message format (topic and JSON payload);
* :mod:`fleetbrake.bridge.sessions`: each wagon's samples held in sessions until written;
* :mod:`fleetbrake.bridge.landing`: durable, atomic, deduplicated writing of the files;
* :mod:`fleetbrake.bridge.mqtt`: the MQTT client, acknowledgements, reconnection, stopping;
* :mod:`fleetbrake.cli.bridge`: the ``bridge`` commands (``register(app)``).

At the ``app`` layer: it imports the log format (:mod:`fleetbrake.fleet`) and the error tree,
and nothing of the warehouse or above. Operating it: ``docs/operations.md``. Nothing is
imported here, so that the command line starts without paho-mqtt and polars; import from the
modules: ``from fleetbrake.bridge.mqtt import run_bridge``.
"""
