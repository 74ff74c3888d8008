"""Optical and sampling parameters of an acquisition, with their physical checks.

All lengths are in micrometres. See ``docs/format.md`` for the meaning of each field and
``docs/physics.md`` for the conventions.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Mapping

from napari_fdt.errors import FDTInputError

__all__ = ["Optics", "OPTICS_FIELDS"]

#: The optical fields of ``acquisition.json``, in the order they are documented.
OPTICS_FIELDS = (
    "wavelength_um",
    "n_background",
    "na",
    "pixel_size_um",
    "n_slices",
    "slice_spacing_um",
    "image_plane_um",
)


def _finite_number(field: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise FDTInputError(field, f"must be a number, got {value!r}", "write a plain JSON number")
    value = float(value)
    if not math.isfinite(value):
        raise FDTInputError(field, f"must be finite, got {value!r}", "write a finite number")
    return value


def _positive(field: str, value: Any, unit: str = "µm") -> float:
    value = _finite_number(field, value)
    if value <= 0:
        raise FDTInputError(field, f"must be positive, got {value:g}", f"give it in {unit}, > 0")
    return value


@dataclass(frozen=True)
class Optics:
    """Optics of the microscope and sampling of the RI volume.

    Attributes
    ----------
    wavelength_um:
        Vacuum wavelength of the detected fluorescence, µm.
    n_background:
        Refractive index of the homogeneous background medium (spacer and surroundings).
    na:
        Numerical aperture of the detection objective; must be below ``n_background``.
    pixel_size_um:
        Lateral sampling of the images and of the RI grid in sample space, µm.
    n_slices:
        Number of slices of the RI volume along z.
    slice_spacing_um:
        Thickness of one slice (distance between slice centres), µm.
    image_plane_um:
        Distance of the camera's focal plane below the volume's top face, µm (0: the top face;
        positive: inside the volume; negative: above it).
    """

    wavelength_um: float
    n_background: float
    na: float
    pixel_size_um: float
    n_slices: int
    slice_spacing_um: float
    image_plane_um: float = 0.0

    def __post_init__(self) -> None:
        # Normalise and check every field; frozen dataclass, so use object.__setattr__.
        set_ = object.__setattr__
        set_(self, "wavelength_um", _positive("wavelength_um", self.wavelength_um))
        n_b = _finite_number("n_background", self.n_background)
        if n_b < 1.0:
            raise FDTInputError(
                "n_background", f"must be >= 1 (a physical medium), got {n_b:g}",
                "give the refractive index of the medium, e.g. 1.33 for water",
            )
        set_(self, "n_background", n_b)
        na = _positive("na", self.na, unit="NA units")
        if na >= n_b:
            raise FDTInputError(
                "na", f"numerical aperture {na:g} is not below n_background {n_b:g}",
                "an objective cannot collect light beyond the medium's index: check na and n_background",
            )
        set_(self, "na", na)
        set_(self, "pixel_size_um", _positive("pixel_size_um", self.pixel_size_um))
        n_slices = self.n_slices
        if isinstance(n_slices, bool) or not isinstance(n_slices, (int, float)) or int(n_slices) != n_slices:
            raise FDTInputError("n_slices", f"must be a whole number, got {n_slices!r}", "write an integer >= 1")
        if int(n_slices) < 1:
            raise FDTInputError("n_slices", f"must be >= 1, got {n_slices!r}", "write an integer >= 1")
        set_(self, "n_slices", int(n_slices))
        set_(self, "slice_spacing_um", _positive("slice_spacing_um", self.slice_spacing_um))
        set_(self, "image_plane_um", _finite_number("image_plane_um", self.image_plane_um))

    @property
    def thickness_um(self) -> float:
        """Thickness of the RI volume, ``n_slices * slice_spacing_um``, µm."""
        return self.n_slices * self.slice_spacing_um

    @property
    def wavenumber_per_um(self) -> float:
        """Spatial frequency of a plane wave in the medium, ``n_background / wavelength_um``, cycles/µm."""
        return self.n_background / self.wavelength_um

    def to_dict(self) -> dict[str, Any]:
        """The optics as the ``acquisition.json`` fields."""
        return asdict(self)

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any]) -> "Optics":
        """Build from a mapping holding every field of :data:`OPTICS_FIELDS` (``image_plane_um`` optional)."""
        missing = [f for f in OPTICS_FIELDS if f not in data and f != "image_plane_um"]
        if missing:
            raise FDTInputError(
                missing[0], "is missing", f"add it to acquisition.json; required: {', '.join(OPTICS_FIELDS[:-1])}"
            )
        return cls(**{f: data[f] for f in OPTICS_FIELDS if f in data})
