"""Which model each stage of a run uses, answered once (issue 52, item 4).

The run's camera model (:class:`CameraModel`: the pupil's edge and the camera's pixel integration as the settings, the
acquisition or the physics state them) is resolved once per run. Each stage's model (:class:`StageSpec`: envelope or
multi-slice, screens per slice, the field grid, obliquity, the camera) follows from the settings, the run's coarse
model and the model parts now on by one rule, :func:`stage_spec`, which the solver's stages, the plan's prices, the
memory check and the stages' roles all read. Only the field window is planned again when a stage is built: it
follows the sources, which the calibration moves.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Collection

from napari_fdt.recon.settings.config import SolverConfig, grid_to_choose

__all__ = ["AUTO_SUB_SLICES", "CameraModel", "StageSpec", "runs_envelope", "rerun_coarse_model", "stage_sub_slices", "stage_field_oversampling", "fine_field_grid",
           "stage_spec"]

#: Screens per slice of the ``"auto"`` sub-slices part where it is on (docs/physics.md, "Sub-slices": 2 take the thin
#: screen's image error from 1.1-6.6 % to 0.2-1.4 % on the suite at 1.3-1.9x the forward pass; 4 leave 0.05-0.3 % at 1.7-2.8x).
AUTO_SUB_SLICES = 2


@dataclass(frozen=True)
class CameraModel:
    """The camera's side of every multi-slice stage, one per run: ``pupil_edge`` (the pupil's soft edge, a fraction of
    the cut-off) and ``pixel_integration`` (images as means over the camera's pixels; before any model part's choice)."""

    pupil_edge: float
    pixel_integration: bool

    def parts_on(self) -> frozenset[str]:
        """The parts on before any choice, as far as the camera decides them: pixel integration where stated or needed."""
        return frozenset({"pixel_integration"}) if self.pixel_integration else frozenset()


def runs_envelope(factor: int, coarse_model: str) -> bool:
    """Whether a stage of ``factor`` runs the envelope model: a coarse stage (factor > 1) where the run's resolved
    ``coarse_model`` is ``"envelope"``."""
    return factor > 1 and coarse_model == "envelope"


def rerun_coarse_model(setting: str, resolved: str) -> str:
    """The coarse stages' model when every stage runs again with kept model parts: multi-slice where the setting
    ``coarse_model`` is ``"auto"`` (the envelope model holds none of the parts), else ``resolved``, the run's (a coarse
    model given by name is kept)."""
    return "multislice" if setting == "auto" else resolved


def stage_sub_slices(setting: int | str, part_on: bool, factor: int) -> int:
    """Screens per slice of a multi-slice stage of ``factor``: the ``sub_slices`` setting when a number (every multi-slice
    stage); for ``"auto"``, :data:`AUTO_SUB_SLICES` in factor-1 stages where the part is on (coarse stages keep one screen
    per slice, as they keep the camera grid under ``field_oversampling``), else 1."""
    if setting != "auto":
        return int(setting)
    return AUTO_SUB_SLICES if part_on and factor == 1 else 1


def stage_field_oversampling(setting: int | str, part_on: bool) -> int:
    """The field grid's factor over the camera's for the ``field_oversampling`` setting: the number when given; for
    ``"auto"`` and ``"before_spectral"`` 2 where the part (``field_grid``) is on, else 1 (it applies to factor-1 stages:
    :func:`fine_field_grid`)."""
    if not grid_to_choose(setting):
        return int(setting)
    return 2 if part_on else 1


def fine_field_grid(field_oversampling: int | str, factor: int) -> bool:
    """Whether a multi-slice stage of ``factor`` runs its field on the 2× grid (:class:`~napari_fdt.model.oversampled.OversampledModel`):
    ``field_oversampling`` 2 applies to factor-1 stages only (coarse stages keep their grids); ``"auto"`` is 1 until the
    part is chosen (:func:`stage_field_oversampling`)."""
    return field_oversampling == 2 and factor == 1


@dataclass(frozen=True)
class StageSpec:
    """The model of one stage (``index`` −1: the acquisition's grid after a run, :meth:`Reconstructor.evaluation_stage`).

    ``sub_slices`` and ``field_oversampling`` are the multi-slice model's (an envelope stage has one screen per slice and
    the camera grid); ``obliquity`` ``"per_source"`` or ``"none"``; the camera's ``pupil_edge`` and ``pixel_integration``
    with the parts applied."""

    index: int
    factor: int
    envelope: bool
    sub_slices: int
    field_oversampling: int
    obliquity: str
    pupil_edge: float
    pixel_integration: bool
    backward_mode: str
    field_window: str

    @property
    def fine_grid(self) -> bool:
        """The field on a grid twice as fine as the camera's (a factor-1 multi-slice stage with the 2× grid)."""
        return not self.envelope and fine_field_grid(self.field_oversampling, self.factor)

    @property
    def screens_per_slice(self) -> int:
        """Thin screens per slice the stage's model runs (1 for an envelope stage)."""
        return 1 if self.envelope else self.sub_slices

    def model_options(self) -> dict[str, Any]:
        """The keywords of :func:`~napari_fdt.recon.problem.stages.build_stage` for this stage's model."""
        return dict(backward_mode=self.backward_mode, sub_slices=self.sub_slices, field_oversampling=self.field_oversampling,
                    field_window=self.field_window, obliquity=self.obliquity, pupil_edge=self.pupil_edge,
                    pixel_integration=self.pixel_integration)


def stage_spec(config: SolverConfig, index: int, coarse_model: str, parts_on: Collection[str], camera: CameraModel,
               factor: int | None = None) -> StageSpec:
    """Stage ``index``'s model under ``config``, the run's resolved ``coarse_model`` and the model parts in ``parts_on``
    (names of :data:`~napari_fdt.recon.loop.model_parts.PARTS` now on, ``pixel_integration`` among them where the camera
    integrates: :meth:`CameraModel.parts_on` before any choice). ``factor``: the stage's (default the configuration's;
    give it with ``index`` −1)."""
    factor = config.stages[index].factor if factor is None else factor
    return StageSpec(
        index=index, factor=factor, envelope=runs_envelope(factor, coarse_model),
        sub_slices=stage_sub_slices(config.sub_slices, "sub_slices" in parts_on, factor),
        field_oversampling=stage_field_oversampling(config.field_oversampling, "field_grid" in parts_on),
        obliquity="per_source" if "obliquity" in parts_on else "none",
        pupil_edge=camera.pupil_edge,
        pixel_integration="pixel_integration" in parts_on,
        backward_mode=config.backward_mode, field_window=config.field_window)
