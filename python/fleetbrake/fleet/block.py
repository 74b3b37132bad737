"""The reference block ``cast-iron-bgu`` of ``shared/spec/block-model.md``: geometry and materials.

Coordinates: the wheel axis is z; the block is centred on +y; a point at radius ``r`` and
angle ``theta`` (from +y towards +x) is ``x = r sin(theta)``, ``y = r cos(theta)``.
Everything is SI (metres, kelvin or degrees Celsius as named); angles are named ``_deg``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

__all__ = [
    "BLOCK_MATERIAL",
    "DEFAULT_AMBIENT_C",
    "DEFAULT_CONVECTION_W_M2K",
    "WHEEL_MATERIAL",
    "BlockGeometry",
    "Material",
    "sensor_point_m",
]

DEFAULT_CONVECTION_W_M2K = 10.0
"""Convection coefficient on every surface but the friction face (paper)."""

DEFAULT_AMBIENT_C = 10.0
"""Ambient temperature of the paper's tests."""


@dataclass(frozen=True)
class BlockGeometry:
    """Dimensions of one block insert: body (a ring sector) and lug (the prominence on its back).

    Every dimension is a parameter: a worn block is a thinner body, another block other numbers.
    """

    wheel_radius_m: float = 0.460
    contact_angle_deg: float = 29.4
    block_width_m: float = 0.080
    body_thickness_m: float = 0.045
    lug_height_m: float = 0.025
    lug_angle_deg: float = 8.0
    lug_width_m: float = 0.040

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
                raise ValueError(f"BlockGeometry.{f.name} must be a positive number, got {value!r}")
        if self.lug_angle_deg >= self.contact_angle_deg:
            raise ValueError(
                f"BlockGeometry.lug_angle_deg ({self.lug_angle_deg}) must be smaller than "
                f"contact_angle_deg ({self.contact_angle_deg})"
            )
        if self.lug_width_m >= self.block_width_m:
            raise ValueError(
                f"BlockGeometry.lug_width_m ({self.lug_width_m}) must be smaller than "
                f"block_width_m ({self.block_width_m})"
            )
        if self.contact_angle_deg >= 180.0:
            raise ValueError("BlockGeometry.contact_angle_deg must be below 180")

    @property
    def contact_angle_rad(self) -> float:
        return math.radians(self.contact_angle_deg)

    @property
    def contact_arc_m(self) -> float:
        """L_b = R_w theta_c, the length of the friction face along the wheel."""
        return self.wheel_radius_m * self.contact_angle_rad

    @property
    def contact_area_m2(self) -> float:
        """A_contact = R_w theta_c H_b, the area of the friction face."""
        return self.contact_arc_m * self.block_width_m


@dataclass(frozen=True)
class Material:
    """Isotropic, temperature-independent thermal properties."""

    conductivity_w_mk: float
    density_kg_m3: float
    specific_heat_j_kgk: float

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
                raise ValueError(f"Material.{f.name} must be a positive number, got {value!r}")

    @property
    def effusivity(self) -> float:
        """beta = sqrt(k rho c), in W s^0.5 / (m^2 K)."""
        return math.sqrt(self.conductivity_w_mk * self.density_kg_m3 * self.specific_heat_j_kgk)

    @property
    def diffusivity_m2_s(self) -> float:
        return self.conductivity_w_mk / (self.density_kg_m3 * self.specific_heat_j_kgk)


BLOCK_MATERIAL = Material(conductivity_w_mk=48.0, density_kg_m3=7100.0, specific_heat_j_kgk=520.0)
"""Cast iron of the block (paper, Table 1)."""

WHEEL_MATERIAL = Material(conductivity_w_mk=45.0, density_kg_m3=7850.0, specific_heat_j_kgk=460.0)
"""Wheel steel, used only in the heat partition (handbook values; an assumption of the spec)."""


def sensor_point_m(
    geometry: BlockGeometry,
    depth_m: float = 0.055,
    theta_deg: float = 0.0,
    z_m: float = 0.0,
) -> tuple[float, float, float]:
    """Cartesian position of the sensor seat: ``depth_m`` radially behind the friction face."""
    r = geometry.wheel_radius_m + depth_m
    theta = math.radians(theta_deg)
    return (r * math.sin(theta), r * math.cos(theta), z_m)
