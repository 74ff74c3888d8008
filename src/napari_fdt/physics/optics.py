"""Optical and sampling parameters of an acquisition, with their physical checks.

All lengths are in micrometres. See ``docs/format.md`` for the meaning of each field and
``docs/physics.md`` for the conventions. The fields are declared with the settings schema
(:mod:`napari_fdt.schema`): ``fdt simulate``'s optics flags and the napari acquisition widget read their
descriptions and example values from it.
"""

from __future__ import annotations

import typing
from dataclasses import asdict
from typing import Any, Mapping

from pydantic import BeforeValidator, model_validator

from napari_fdt.errors import FDTInputError
from napari_fdt.schema import example, schema_dataclass, schema_fields, setting

__all__ = ["Optics", "OPTICS_FIELDS"]


def _whole_number(value: Any) -> Any:
    """A whole float (``14.0``, as JSON may write it) as an ``int``; anything else unchanged for the strict
    integer check."""
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


_SliceCount = typing.Annotated[int, BeforeValidator(_whole_number)]


@schema_dataclass(frozen=True, root="optics")
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

    wavelength_um: float = setting(gt=0, example=0.635, description="vacuum emission wavelength, µm", fix="give it in µm, > 0")
    n_background: float = setting(ge=1, example=1.33, description="background refractive index",
                                  fix="give the refractive index of the medium, e.g. 1.33 for water")
    na: float = setting(gt=0, example=0.8, description="detection numerical aperture (below n_background)", fix="give it in NA units, > 0")
    pixel_size_um: float = setting(gt=0, example=0.33, description="lateral sampling in the sample, µm", fix="give it in µm, > 0")
    n_slices: _SliceCount = setting(ge=1, example=8, description="slices of the RI volume", fix="write an integer >= 1")
    slice_spacing_um: float = setting(gt=0, example=2.0, description="slice thickness, µm", fix="give it in µm, > 0")
    image_plane_um: float = setting(0.0, example=0.0, description="camera focal plane below the volume's top face, µm",
                                    fix="write a finite number")

    @model_validator(mode="after")
    def _aperture_below_medium(self) -> "Optics":
        if self.na >= self.n_background:
            raise FDTInputError(
                "na", f"numerical aperture {self.na:g} is not below n_background {self.n_background:g}",
                "an objective cannot collect light beyond the medium's index: check na and n_background",
            )
        return self

    @property
    def thickness_um(self) -> float:
        """Thickness of the RI volume, ``n_slices * slice_spacing_um``, µm."""
        return self.n_slices * self.slice_spacing_um

    @property
    def wavenumber_per_um(self) -> float:
        """Spatial frequency of a plane wave in the medium, ``n_background / wavelength_um``, cycles/µm."""
        return self.n_background / self.wavelength_um

    @property
    def depth_of_field_um(self) -> float:
        """Depth of field of the light the pupil passes, ``λ/(n_b·(1 − cos θ))`` with ``sin θ = NA/n_b``, µm: a slice much
        thinner than this is a thin screen; at 0.84 of it (2 µm slices, NA 0.8) one screen per slice is 1–7 % off a
        continuous slab (docs/physics.md, "Sub-slices")."""
        import math

        s = self.na / self.n_background
        return self.wavelength_um / (self.n_background * (1.0 - math.sqrt(max(0.0, 1.0 - s * s))))

    def to_dict(self) -> dict[str, Any]:
        """The optics as the ``acquisition.json`` fields."""
        return asdict(self)

    @classmethod
    def examples(cls) -> dict[str, Any]:
        """Example value of every field (those of ``fdt simulate``), e.g. to prefill a form."""
        return {name: example(info) for name, info in schema_fields(cls).items()}

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any]) -> "Optics":
        """Build from a mapping holding every field of :data:`OPTICS_FIELDS` (``image_plane_um`` optional)."""
        missing = [f for f in OPTICS_FIELDS if f not in data and f != "image_plane_um"]
        if missing:
            raise FDTInputError(
                missing[0], "is missing", f"add it to acquisition.json; required: {', '.join(OPTICS_FIELDS[:-1])}"
            )
        return cls(**{f: data[f] for f in OPTICS_FIELDS if f in data})


#: The optical fields of ``acquisition.json``, in the order they are documented.
OPTICS_FIELDS: tuple[str, ...] = tuple(schema_fields(Optics))
