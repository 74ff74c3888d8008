"""The resolution of a finished run from two half-set reconstructions (``half_set_resolution``; issue 25).

What size of structure can a user believe? As cryo-EM does with half maps: the images are split in two halves that
each cover the illumination like the whole (:func:`~napari_fdt.recon.assess.validation.split_halves`), each half is reconstructed from nothing with the
run's own choices fixed (:func:`chosen_settings`: the TV weights and model parts the run chose, so the halves make the
same decisions without trials), and the two volumes are compared by their Fourier shell correlation, lateral and
axial (:mod:`napari_fdt.recon.assess.fsc`). The resolution is the period where the halves' FSC falls below 1/7, where the
whole volume's FSC with the truth is about 0.5, or the optics' band limit where that is coarser
(:mod:`napari_fdt.physics.band`: finer structure leaves no first-order trace in any image, so agreement there is the
regulariser's and the grid's), or the grid's Nyquist period where the halves agree up to it.

What it can and cannot see: the halves are independent in their data and their noise, not in what both miss. Structure
no image constrains is filled the same way in both by the same regulariser, and a model error is made by both: that
counts as agreement. The band limit takes out the frequencies beyond the optics' reach; inside the band, the figure is
still an upper bound on what the data resolve. Checked against the truth on the suite (docs/decisions/tv-half-sets.md,
section 8).

Cost: two more runs on half of the images each (the same stages and batch; the finest stage is lengthened to its
minimum passes over the half's images, :func:`napari_fdt.recon.settings.config.resolve_stage_lengths`).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.errors import FDTWarning
from napari_fdt.physics.band import band_limit_per_um
from napari_fdt.recon.assess.fsc import HALF_SET_THRESHOLD, FscCurve, Resolution, fsc_curves, resolution
from napari_fdt.recon.assess.validation import split_halves
from napari_fdt.recon.loop.model_parts import SETTING_OF
from napari_fdt.recon.problem.stage_spec import AUTO_SUB_SLICES
from napari_fdt.recon.settings.config import AUTO, SolverConfig

if TYPE_CHECKING:
    from napari_fdt.recon.run.solver import Reconstructor

__all__ = ["chosen_settings", "resolution_figure", "HalfSetResolution", "half_set_resolution", "describe_bound", "describe_bounds",
           "describe_resolution"]

#: A part's setting when the run chose it off, and on (parts with a number or a model name; the others are booleans).
#: The spectral model on stays "auto": which coherence model goes with it is the half's own choice.
_OFF = {"sub_slices": 1, "field_grid": 1, "spectral": "none"}
_ON = {"sub_slices": AUTO_SUB_SLICES, "field_grid": 2, "spectral": AUTO}


def chosen_settings(rec: Reconstructor) -> SolverConfig:
    """``rec``'s settings with what the run chose fixed: the TV weights in force at its end and every ``"auto"`` model
    part as the run left it (on or off; the spectral model on stays ``"auto"``, for the half to choose its coherence
    model); no pupil pilot, no half-set estimate of its own."""
    d = rec.requested_config.to_dict()
    d.update(tv_xy_weight=float(rec.loss_weights.tv_xy), tv_z_weight=float(rec.loss_weights.tv_z), parts_pilot=False,
             half_set_resolution=False)
    for part, on in rec.parts.items():
        key = SETTING_OF[part]
        if d.get(key) != AUTO:
            continue
        if part in _OFF:
            d[key] = _ON[part] if on else _OFF[part]
        else:
            d[key] = bool(on)
    return SolverConfig.from_dict(d)


def resolution_figure(half_sets_um: float | None, grid_um: float, band_um: float) -> tuple[float, str]:
    """The figure reported (µm) from the halves' crossing (None: none up to the grid), the grid's Nyquist period and the
    band limit's period, and what sets it: ``"band"`` (no image carries finer: the band limit is the coarsest),
    ``"halves"`` (where their FSC falls below 1/7) or ``"grid"`` (the halves agree up to it and the band reaches beyond)."""
    halves_um = grid_um if half_sets_um is None else half_sets_um
    if band_um >= halves_um:
        return band_um, "band"
    return halves_um, "grid" if half_sets_um is None else "halves"


@dataclass
class HalfSetResolution:
    """The half-set comparison: each direction's FSC curve and where it falls below 1/7 (``found``), the optics' band
    limit (cycles/µm, :func:`napari_fdt.physics.band.band_limit_per_um`), the halves' image counts and the seconds."""

    curves: dict[str, FscCurve]
    found: dict[str, Resolution]
    band_per_um: dict[str, float]
    n_images: tuple[int, int]
    seconds: float

    def figure(self, direction: str) -> tuple[float, str]:
        """The resolution (µm) in ``direction`` and what sets it (:func:`resolution_figure`)."""
        found = self.found[direction]
        return resolution_figure(found.resolution_um, found.grid_limit_um, 1.0 / self.band_per_um[direction])

    def to_dict(self) -> dict[str, Any]:
        directions = {}
        for d, curve in self.curves.items():
            um, by = self.figure(d)
            directions[d] = {"resolution_um": um, "limited_by": by, "half_sets_um": self.found[d].resolution_um,
                             "band_limit_um": 1.0 / self.band_per_um[d], "grid_limit_um": curve.grid_limit_um,
                             "fsc": curve.to_dict()}
        return {"method": "half-set FSC", "threshold": round(HALF_SET_THRESHOLD, 4), "n_images": list(self.n_images),
                "seconds": round(self.seconds, 2), **{f"{d}_um": directions[d]["resolution_um"] for d in directions},
                "directions": directions}


_LIMITS = {"grid": "the grid: the halves agree up to it", "band": "the optics' band limit", "halves": "where the halves part"}


def describe_bound(summary: dict[str, Any], direction: str) -> str:
    """One direction's figure for people from :meth:`HalfSetResolution.to_dict`: the period in µm and what sets it."""
    r = summary["directions"][direction]
    return f"{'≤ ' if r['limited_by'] == 'grid' else ''}{r['resolution_um']:.2g} µm ({_LIMITS[r['limited_by']]})"


def describe_bounds(summary: dict[str, Any]) -> str:
    """``lateral …, axial …`` (:func:`describe_bound`): the widget's result line and the CLI's."""
    return f"lateral {describe_bound(summary, 'lateral')}, axial {describe_bound(summary, 'axial')}"


def describe_resolution(summary: dict[str, Any]) -> str:
    """One line for people (the CLI) from :meth:`HalfSetResolution.to_dict`."""
    a, b = summary["n_images"]
    return (f"resolution (half-set FSC at 1/7, {a} + {b} images, {summary['seconds']:.0f} s): "
            f"{describe_bounds(summary)}. Finer structure is not "
            "resolved; coarser structure is at best: an error both halves share (a model error, what no image constrains "
            "inside the band) is not seen")


def half_set_resolution(rec: Reconstructor, *, should_stop: Callable[[], bool] | None = None,
                        on_half: Callable[[int], None] | None = None) -> HalfSetResolution | None:
    """Reconstruct each half of ``rec``'s images with :func:`chosen_settings` from the run's starting positions, on its
    device, and compare the two Δn volumes. ``on_half(i)`` is called as half ``i`` (0, 1) starts; ``should_stop`` is
    polled between iterations (None returned when it stopped a half)."""
    from napari_fdt.recon.run.solver import Reconstructor

    acq = rec.acquisition
    config = chosen_settings(rec)
    start_um = rec.initial_sources_um
    t0 = time.perf_counter()
    volumes = []
    halves = split_halves(start_um, rec.config.seed)
    for i, idx in enumerate(halves):
        if on_half is not None:
            on_half(i)
        sub = Acquisition(images=acq.images[idx], optics=acq.optics,
                          sources_um=None if acq.sources_um is None else acq.sources_um[idx], extra=dict(acq.extra))
        with warnings.catch_warnings():  # what the run said of the data it says once; a half's own (too few images to
            warnings.simplefilter("ignore", FDTWarning)  # hold some out) concern this estimate's inner runs only
            half = Reconstructor(sub, config, device=rec.device, initial_sources_um=start_um[idx])
            for _ in half.run(should_stop=should_stop):
                pass
        if half.completed_stages < len(half.config.stages):
            return None
        volumes.append(half.delta_n_full())
    o = acq.optics
    curves = fsc_curves(volumes[0], volumes[1], o.pixel_size_um, o.slice_spacing_um)
    found = {d: resolution(c, HALF_SET_THRESHOLD) for d, c in curves.items()}
    band = band_limit_per_um(o, acq.image_shape, start_um)
    return HalfSetResolution(curves, found, band, (len(halves[0]), len(halves[1])), time.perf_counter() - t0)


