"""The reduced models the package ships (``rom-<key>.npz``), written by
``python -m fleetbrake.model.romdata``; read by :meth:`fleetbrake.model.rom.ReducedModel.cached`."""
