"""fleetbrake: thermal watch over the cast-iron brake blocks of a freight-wagon fleet.

SI units inside; every name that carries a quantity says its unit (``dt_s``, ``temp_c``,
``flux_w_m2``). The finite-element core is Rust (``fleetbrake._ext``); this package holds
the physics, validation, defaults and everything a user touches.
"""

from __future__ import annotations

__version__ = "0.1.0"
