"""The reproduction of the paper's Ansys study: manoeuvres A and B, calibration, the study, the
figures and VTU fields (``fleetbrake paper``; ``docs/paper-reproduction.md``).

Modules, each importing only those above it:

- :mod:`.settings`: how it is run (``RunSettings``), the wagon, the studied values;
- :mod:`.peaks`: the refined maximum of a sampled curve;
- :mod:`.results`: the typed results (``ManoeuvreResult``, ``Calibration``,
  ``PaperReproduction``, ``Study``), each with ``to_dict()`` for the JSON;
- :mod:`.reproduction`: the computation: one manoeuvre, the calibration, the reproduction,
  linear superposition;
- :mod:`.study`: the study (depth, convection, bore, what-ifs) and the re-meshing check;
- :mod:`.report` (console tables), :mod:`.plots` (PNG), :mod:`.export` (VTU) and
  :mod:`.outputs` (the files of ``--out``): the outputs, reading the results.
"""
