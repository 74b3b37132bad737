"""What people look at: rerun recordings of a wagon's timeline or of one event
(``fleetbrake record``).

Modules, each importing only those above it:

- :mod:`.entities`: the recording's timeline and entity paths;
- :mod:`.data`: what a recording shows, read from the warehouse (``q_record_*.sql``), and
  the errors naming what is missing;
- :mod:`.timeline`: one ``log_<thing>()`` per concern of the timeline (speed, pressure,
  temperatures, residual, events, flags, faulty readings, notes);
- :mod:`.block`: the block's temperature field through one event, simulated and logged;
- :mod:`.blueprint`: the layout;
- :mod:`.record`: :func:`~fleetbrake.viz.record.record`, which puts them together into a file.
"""
