"""What the fleet is: its registry of wagons and their blocks (geometry, materials), and the
on-board units' log files (format, names, reading). The lowest layer: imports nothing of fleetbrake
but :mod:`fleetbrake.errors`."""
