"""The jobs users run, each composed of the layers below: ``run`` (files to flags), the fleet
report, and the demo."""
