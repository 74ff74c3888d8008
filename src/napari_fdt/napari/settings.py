"""Solver settings as the reconstruction widget shows them: the stage list as text, and checked configs.

The widget edits a subset of :class:`~napari_fdt.recon.settings.config.SolverConfig`; the other settings keep the
values of the last loaded settings file (or the defaults), so that saving writes a complete file in the
format of ``fdt reconstruct --config``.
"""

from __future__ import annotations

import re
from typing import Any

from napari_fdt.errors import FDTInputError
from napari_fdt.physics.optics import Optics
from napari_fdt.recon.settings.command import unique_path  # noqa: F401 (re-exported: it lived here)
from napari_fdt.recon.settings.config import SolverConfig, StageConfig

__all__ = [
    "format_stages", "parse_stages", "merge_config", "OPTICS_LABELS", "OPTICS_OPTIONAL", "format_entry", "missing_optics",
    "optics_from_entries", "unique_path",
]

_STAGE = re.compile(r"^\s*(\d+)\s*[x×:*]\s*(\d+)\s*(?:@\s*(\d+)\s*)?$")
_STAGES_FIX = ("write factor x iterations per stage, comma separated, e.g. 4x100, 2x100, 1x160 "
               "(a stage's own batch size after @, e.g. 4x100@64)")


def format_stages(stages: list[StageConfig]) -> str:
    """``[StageConfig(4, 100, 64), StageConfig(1, 160)]`` → ``"4x100@64, 1x160"`` (``@`` a stage's own batch size)."""
    return ", ".join(f"{s.factor}x{s.iterations}" + ("" if s.batch_size is None else f"@{s.batch_size}") for s in stages)


def parse_stages(text: str) -> list[dict[str, int]]:
    """``"4x100, 2x100, 1x160"`` (also ``×``, ``:`` or ``*``; ``4x100@64`` gives the stage batch 64) →
    ``[{"factor": 4, "iterations": 100}, …]``."""
    parts = [p for p in str(text).split(",") if p.strip()]
    if not parts:
        raise FDTInputError("stages", "is empty", _STAGES_FIX)
    out = []
    for part in parts:
        m = _STAGE.match(part)
        if not m:
            raise FDTInputError("stages", f"cannot read {part.strip()!r}", _STAGES_FIX)
        stage = {"factor": int(m.group(1)), "iterations": int(m.group(2))}
        if m.group(3) is not None:
            stage["batch_size"] = int(m.group(3))
        out.append(stage)
    return out


def merge_config(base: SolverConfig, values: dict[str, Any]) -> SolverConfig:
    """``base`` with ``values`` replaced (``stages`` may be the widget's text), validated by :class:`SolverConfig`."""
    data = base.to_dict()
    values = dict(values)
    if isinstance(values.get("stages"), str):
        values["stages"] = parse_stages(values["stages"])
    data.update(values)
    return SolverConfig.from_dict(data)


# -- optics as the acquisition widget shows them: text fields, empty until the file or the user gives them --------

#: The label of every optics field in the widget, in plain words (errors name the field by its label; the tooltips,
#: ``napari_fdt.napari.widgets.widget_acquisition.OPTICS_TIPS``, start with the field's name in the files and the API).
OPTICS_LABELS: dict[str, str] = {
    "wavelength_um": "emission wavelength (µm)", "n_background": "medium refractive index", "na": "objective NA",
    "pixel_size_um": "pixel size in sample (µm)", "n_slices": "number of slices", "slice_spacing_um": "slice thickness (µm)",
    "image_plane_um": "focal plane depth (µm)",
}
#: Fields that may stay empty, with the value an empty field means (``Optics``' own default).
OPTICS_OPTIONAL: dict[str, float] = {"image_plane_um": 0.0}

#: Plausible ranges (µm) of light microscopy; a value outside is refused with the likely unit mistake.
WAVELENGTH_RANGE_UM = (0.3, 2.0)
PIXEL_SIZE_RANGE_UM = (0.02, 20.0)


def format_entry(value: Any) -> str:
    """A number as the widget's text field shows it (``0.635``, ``8``); ``""`` for None."""
    if value is None:
        return ""
    if isinstance(value, (int,)) and not isinstance(value, bool):
        return str(value)
    return f"{float(value):.10g}"


def missing_optics(entries: dict[str, str]) -> list[str]:
    """Labels of the required optics fields that are empty in ``entries`` (field → text)."""
    return [OPTICS_LABELS[name] for name in OPTICS_LABELS
            if name not in OPTICS_OPTIONAL and not str(entries.get(name, "") or "").strip()]


def _number(name: str, text: str) -> float:
    label = OPTICS_LABELS[name]
    try:
        value = float(str(text).strip().replace(",", "."))
    except ValueError:
        raise FDTInputError(label, f"{str(text).strip()!r} is not a number", "type a number, e.g. 0.635") from None
    return value


def _unit_hint(label: str, value: float, lo: float, hi: float, what: str) -> FDTInputError:
    """The error for a length outside [lo, hi] µm, naming the unit it was likely typed in."""
    for unit, to_um in (("nm", 1e-3), ("mm", 1e3), ("m", 1e6)):
        if lo <= value * to_um <= hi:
            return FDTInputError(label, f"{value:g} looks like {unit}, not µm",
                                 f"enter {value * to_um:g}: the field takes µm, and {what} lies between {lo:g} and {hi:g} µm")
    return FDTInputError(label, f"{value:g} µm is outside {lo:g} to {hi:g} µm", f"enter the {what} in µm")


def optics_from_entries(entries: dict[str, str]) -> Optics:
    """The optics typed in the widget (field → text), checked; raises :class:`FDTInputError` naming the widget's label.

    Empty required fields are refused by name; a wavelength outside 0.3–2 µm, a pixel size outside 0.02–20 µm or
    an NA not below the medium refractive index are refused with the likely mistake (e.g. ``635 looks like nm``); then
    :class:`~napari_fdt.physics.optics.Optics` checks the rest (its message relabelled with the widget's words).
    """
    missing = missing_optics(entries)
    if missing:
        raise FDTInputError(missing[0], "is empty",
                            f"enter {', '.join(missing)} (from the microscope's settings) and press Apply optics")
    values: dict[str, Any] = {}
    for name in OPTICS_LABELS:
        text = str(entries.get(name, "") or "").strip()
        values[name] = OPTICS_OPTIONAL[name] if not text else _number(name, text)
    lam, dx = values["wavelength_um"], values["pixel_size_um"]
    if lam > 0 and not WAVELENGTH_RANGE_UM[0] <= lam <= WAVELENGTH_RANGE_UM[1]:
        raise _unit_hint(OPTICS_LABELS["wavelength_um"], lam, *WAVELENGTH_RANGE_UM, "the emission wavelength")
    if dx > 0 and not PIXEL_SIZE_RANGE_UM[0] <= dx <= PIXEL_SIZE_RANGE_UM[1]:
        raise _unit_hint(OPTICS_LABELS["pixel_size_um"], dx, *PIXEL_SIZE_RANGE_UM, "the pixel size in the sample")
    na, n_b = values["na"], values["n_background"]
    medium = OPTICS_LABELS["n_background"]
    if na > 0 and n_b >= 1 and na >= n_b:
        hint = (f"{na:g} looks like an angle or a percentage: NA = n·sin(θ) is below the {medium}" if na > 2
                else f"an NA of {na:g} needs an immersion index above it: check the {medium} (oil 1.518, water 1.33)")
        raise FDTInputError(OPTICS_LABELS["na"], f"{na:g} is not below the {medium} {n_b:g}", hint)
    if values["n_slices"] != int(values["n_slices"]):
        raise FDTInputError(OPTICS_LABELS["n_slices"], f"{values['n_slices']:g} is not a whole number", "enter an integer ≥ 1")
    values["n_slices"] = int(values["n_slices"])
    try:
        return Optics(**values)
    except FDTInputError as exc:
        label = OPTICS_LABELS.get(exc.field, exc.field)
        raise FDTInputError(label, exc.problem.replace("n_background", f"the {medium}"), exc.fix) from None


