"""Translucent materials: a homogeneous scattering medium inside a boundary surface.

Units: the extinction ``sigma_t`` is per scene unit (objects fit the unit sphere), so the mean free path
is ``1 / sigma_t`` scene units; ``albedo = sigma_s / sigma_t`` is the single-scattering albedo; ``g`` is
the Henyey-Greenstein asymmetry. The boundary is either ``null`` (index-matched: light enters unrefracted,
the cleanest estimator with point lights) or ``roughdielectric`` (GGX, ``alpha >= 0.05``, relative index
``eta``). A smooth dielectric is refused: with point lights it renders black in Mitsuba (no next-event
estimation through a delta interface), and rough dielectrics are much noisier than null boundaries.

The built-in materials use a grey ``sigma_t`` and put their colour in the albedo: Mitsuba's ``volpath``
samples free-flight distances from one colour channel, so a chromatic extinction produces coloured
fireflies; colour then arises from the albedo compounded over many scattering events.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

RGB = tuple[float, float, float]
Boundary = Literal["null", "roughdielectric"]


@dataclass(frozen=True)
class TranslucentMaterial:
    """Parameters of a homogeneous translucent medium and its boundary."""

    name: str
    albedo: RGB
    sigma_t: RGB
    g: float
    boundary: Boundary = "null"
    eta: float = 1.45
    roughness: float = 0.3

    def __post_init__(self) -> None:
        if len(self.albedo) != 3 or not all(0.0 <= a <= 1.0 for a in self.albedo):
            raise ValueError(f"{self.name}: albedo must be 3 values in [0, 1], got {self.albedo}")
        if len(self.sigma_t) != 3 or not all(s > 0.0 for s in self.sigma_t):
            raise ValueError(f"{self.name}: sigma_t must be 3 positive values, got {self.sigma_t}")
        if not -1.0 < self.g < 1.0:
            raise ValueError(f"{self.name}: HG g must lie in (-1, 1), got {self.g}")
        if self.boundary not in ("null", "roughdielectric"):
            raise ValueError(
                f"{self.name}: boundary must be 'null' or 'roughdielectric', got {self.boundary!r}"
            )
        if self.boundary == "roughdielectric" and not (self.roughness >= 0.05 and 1.0 < self.eta < 3.0):
            raise ValueError(
                f"{self.name}: roughdielectric needs roughness >= 0.05 and 1 < eta < 3, "
                f"got roughness={self.roughness}, eta={self.eta}"
            )

    def medium_dict(self) -> dict:
        """Mitsuba ``homogeneous`` medium: RGB ``sigma_t`` stored as ``value / max * scale``."""
        scale = max(self.sigma_t)
        return {
            "type": "homogeneous",
            "albedo": {"type": "rgb", "value": list(self.albedo)},
            "sigma_t": {"type": "rgb", "value": [s / scale for s in self.sigma_t]},
            "scale": scale,
            "phase": {"type": "hg", "g": self.g},
        }

    def bsdf_dict(self) -> dict:
        """Mitsuba boundary BSDF."""
        if self.boundary == "null":
            return {"type": "null"}
        return {
            "type": "roughdielectric",
            "distribution": "ggx",
            "alpha": self.roughness,
            "int_ior": self.eta,
            "ext_ior": 1.0,
        }


MATERIALS: dict[str, TranslucentMaterial] = {
    m.name: m
    for m in (
        TranslucentMaterial("wax", albedo=(0.985, 0.95, 0.85), sigma_t=(11.0, 11.0, 11.0), g=0.3),
        TranslucentMaterial("jade", albedo=(0.80, 0.97, 0.86), sigma_t=(7.0, 7.0, 7.0), g=0.6),
        TranslucentMaterial("marble", albedo=(0.995, 0.99, 0.975), sigma_t=(25.0, 25.0, 25.0), g=0.0),
        TranslucentMaterial("skin", albedo=(0.97, 0.82, 0.68), sigma_t=(15.0, 15.0, 15.0), g=0.8),
        TranslucentMaterial("soap", albedo=(0.95, 0.90, 0.97), sigma_t=(4.5, 4.5, 4.5), g=0.2),
        TranslucentMaterial(
            "glazed_wax",
            albedo=(0.985, 0.95, 0.85),
            sigma_t=(11.0, 11.0, 11.0),
            g=0.3,
            boundary="roughdielectric",
            eta=1.45,
            roughness=0.4,
        ),
    )
}


def material_names() -> list[str]:
    """Names accepted by :func:`get_material`."""
    return sorted(MATERIALS)


def get_material(name: str) -> TranslucentMaterial:
    """The named material; ``ValueError`` listing the valid names otherwise."""
    if name not in MATERIALS:
        raise ValueError(f"unknown material {name!r}; valid materials: {', '.join(material_names())}")
    return MATERIALS[name]
