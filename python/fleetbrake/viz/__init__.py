"""What people look at: rerun recordings of a wagon's timeline or of one event
(``fleetbrake record``), and the same timelines streamed live to a viewer
(``fleetbrake watch --rerun``).

Modules, each importing only those above it:

- :mod:`.entities`: the recording's timeline and entity paths;
- :mod:`.data`: what a recording shows, read from the warehouse (``q_record_*.sql``), and
  the errors naming what is missing;
- :mod:`.timeline`: one ``log_<thing>()`` per concern of the timeline (speed, pressure,
  temperatures, contact estimate, unexplained power, residual, events, flags, faulty
  readings, notes);
- :mod:`.block`: the block's temperature field through one event, simulated and logged;
- :mod:`.blueprint`: the layout;
- :mod:`.compose`: :func:`~fleetbrake.viz.compose.log_recording`, the one composition of
  them on a recording stream, whatever the sink;
- :mod:`.record`: :func:`~fleetbrake.viz.record.record`, which writes it into a file;
- :mod:`.live`: :class:`~fleetbrake.viz.live.LiveTimelines`, which streams each unit's new
  timelines to a live viewer over gRPC.
"""
