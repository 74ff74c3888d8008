"""The plan of a run: its phases in order, with their iterations and predicted seconds, known before the first iteration.

A *phase* is a stretch of iterations of one kind at one stage: a stage of the pass, the trials of the ``"auto"`` TV
weights at the selection stage (the stages before them marked as part of the choice), or a stage run again with kept model parts
(:mod:`napari_fdt.recon.loop.phases` names the kinds). :func:`make_plan` lists them from the configuration, the
acquisition's geometry and the device, before anything is allocated; the solver counts its progress along the plan
(``Snapshot.plan_iteration`` of ``plan_iterations``: one count for the whole run, never restarted) and :class:`~napari_fdt.recon.loop.pace.Pace`
turns the plan and the times the run measures into one time-left estimate. The command line's bar, the widget and the
report read them. When the choice of model parts keeps a part and the stages run again (``parts_rerun = "stages"``),
:meth:`Plan.with_rerun` appends those phases (the count grows; it never restarts).

**One cost model** (:mod:`napari_fdt.recon.loop.step_cost`): an iteration's seconds from its batch, screens and the
grid its FFTs run on, by device and model.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Sequence

import numpy as np

from napari_fdt.physics.optics import Optics
from napari_fdt.recon.loop.model_parts import PILOT_BATCH, PILOT_ITERATIONS, grid_waits_for_spectral
from napari_fdt.recon.loop.phases import PUPIL_PILOT, RERUN, RUN, TV_CHOICE, probe_iterations
from napari_fdt.recon.loop.regularisation import TV_PATH, selection_stages
from napari_fdt.recon.loop.step_cost import (
    OBLIQUITY_UNITS,
    OVERHEAD_S,
    PILOT_STEP_OVERHEAD_S,
    SECONDS_PER_UNIT,
    envelope_padded_shape,
    iteration_units,
)
from napari_fdt.recon.problem.stage_spec import rerun_coarse_model
from napari_fdt.recon.settings.config import SolverConfig

__all__ = ["Phase", "Plan", "stage_phase", "make_plan", "most_seconds", "plan_for", "seconds_in_words"]

#: What the tests at the finest stage's end are called in the plan (:attr:`Phase.test`; a rerun's are found by it).
PARTS_TEST = "testing the model parts"

#: The finest stage's model parts in words (the plan's summary).
PART_WORDS: dict[str, str] = {"sub_slices": "sub-slices", "field_grid": "the 2x field grid"}


@dataclass(frozen=True)
class Phase:
    """One phase of a run. ``pass_name``: the snapshot's ``phase`` ("tv_choice", "run", "rerun"); ``trials``: the
    trials of the TV weights (``iterations`` for all of them) rather than a stage; ``model`` "envelope" or
    "multislice"; ``fft_shape`` (h, w) px the model's FFTs run on; ``seconds_per_iteration`` the prior prediction;
    ``parts`` the model parts a rerun holds; ``first_iteration`` the stage iterations done before the phase starts
    (the selection stage's rest starts after the winning trial's)."""

    pass_name: str
    stage: int
    n_stages: int
    factor: int
    model: str
    iterations: int
    fft_shape: tuple[int, int]
    seconds_per_iteration: float
    trials: bool = False
    parts: tuple[str, ...] = ()
    first_iteration: int = 0
    #: seconds of the tests at the phase's end (the model parts', :mod:`~napari_fdt.recon.loop.parts_price`) and what
    #: they test, in words
    test_s: float = 0.0
    test: str = ""

    @property
    def iterations_s(self) -> float:
        """The predicted seconds of the phase's iterations (without the tests at its end)."""
        return self.iterations * self.seconds_per_iteration

    @property
    def predicted_s(self) -> float:
        return self.iterations_s + self.test_s

    @property
    def name(self) -> str:
        """The phase in words: "stage 2/3 (x2)", "choosing the TV weight: stage 1/3 (x4) with the lightest TV" (a stage before the
        trials),
        "choosing the TV weight at stage 2/3 (x2)" (the trials), …"""
        where = f"stage {self.stage + 1}/{self.n_stages} (x{self.factor})"
        if self.pass_name == PUPIL_PILOT:
            return "checking the pupil at Δn = 0, before the stages"
        if self.pass_name == TV_CHOICE:
            return f"choosing the TV weight at {where}" if self.trials else f"choosing the TV weight: {where} with the lightest TV"
        if self.pass_name == RERUN or self.parts:  # (a stage run again from its start with kept parts: parts_rerun "finest")
            return f"{where} again with {'+'.join(self.parts)}" if self.parts else f"{where} again"
        return where

    def priced_as(self, other: "Phase", label: bool = False) -> "Phase":
        """This phase with ``other``'s model, FFT grid and seconds per iteration: a stage priced again for the parts a
        choice kept (``other`` from :func:`stage_phase` with them); ``label``: its ``parts`` too (its name says them)."""
        return replace(self, model=other.model, fft_shape=other.fft_shape, seconds_per_iteration=other.seconds_per_iteration,
                       **({"parts": other.parts} if label else {}))

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "phase": self.pass_name, "stage": self.stage, "factor": self.factor, "model": self.model,
                "iterations": self.iterations, "fft_shape": list(self.fft_shape),
                "seconds_per_iteration": self.seconds_per_iteration, "predicted_s": self.predicted_s,
                **({"test": self.test, "test_s": self.test_s} if self.test_s else {})}


@dataclass(frozen=True)
class Plan:
    """The phases of a run, in order (:func:`make_plan`)."""

    phases: tuple[Phase, ...]
    device_type: str
    #: seconds more if the choice of model parts keeps one (every stage then runs again, its coarse stages multi-slice
    #: under ``coarse_model = "auto"``); None where no such choice is to come
    if_part_kept_s: float | None = None
    #: seconds more where a part is found at the last coarse stage's end (the test of
    #: :mod:`~napari_fdt.recon.choices.parts_coarse_end`): every stage again, the first pass's finest stage never run; None where
    #: no such test is planned
    if_part_kept_early_s: float | None = None
    #: the stage of that test
    early_test_stage: int | None = None
    #: seconds more if the choice keeps only parts of the finest stage's model (:data:`finest_parts`: the finest stage
    #: then runs again with them), priced with all of them; None where none is to choose
    if_finest_parts_kept_s: float | None = None
    #: the "auto" parts of the finest stage's model to choose (sub-slices, the 2x field grid)
    finest_parts: tuple[str, ...] = ()
    #: seconds more if a kept part no longer earns its place at the end (``parts_backward``,
    #: :mod:`~napari_fdt.recon.choices.parts_backward`: the finest stage again without it); None where no part is to choose
    if_part_dropped_s: float | None = None
    #: seconds of the half-set resolution after the run (``half_set_resolution``: each half of the images run again, no
    #: trials); None where it is not asked for
    half_sets_s: float | None = None
    #: seconds of the error bound after the run (``error_bounds``: the stages again per re-simulated replicate, no
    #: trials); None where it is not asked for
    bounds_s: float | None = None
    #: seconds more if the part kept is the spectral model (every stage again, one pass per wavelength: 2-5x
    #: :attr:`if_part_kept_s` on beads and cells_fine, 2026-11-28); None where it is not to choose
    if_spectral_kept_s: float | None = None
    #: seconds more where the 2x field grid is tried before a spectral model is kept (``field_oversampling =
    #: "before_spectral"``; :attr:`if_spectral_kept_s` holds the grid's test) and keeps it: the finest stage again on it,
    #: with sub-slices where they are to choose too; None where the grid is not tried so
    if_grid_kept_s: float | None = None
    #: seconds of the whole run where the data ask for the costliest choices: a TV weight larger than the first stages
    #: ran with (they run again), and the costliest model parts of each kind (every stage again with the costliest single
    #: part of the stages' model and the tests again, the finest stage again with its costliest parts, and again at the
    #: end where a kept part is dropped: :func:`most_seconds`), over :attr:`predicted_s`; None where nothing is left to
    #: choose (the choices' revisions take off what they settle: :meth:`tv_chosen`, :meth:`choices_made`)
    most_extra_s: float | None = None
    #: the share of :attr:`most_extra_s` that the TV weight's choice settles (the stages before its trials again)
    tv_again_s: float = 0.0

    @property
    def most_s(self) -> float | None:
        """Seconds of the whole run where the data ask for the costliest choices still open (None: none is)."""
        return None if self.most_extra_s is None else self.predicted_s + self.most_extra_s

    @property
    def range_top_s(self) -> float | None:
        """:attr:`most_s` where it is worth saying beside :attr:`predicted_s` (over 5 % more), else None."""
        return self.most_s if self.most_s is not None and self.most_s > 1.05 * self.predicted_s else None

    @property
    def grid_before_spectral(self) -> bool:
        """Whether the 2x field grid is tried before a spectral model is kept (:attr:`if_grid_kept_s` prices it)."""
        return self.if_grid_kept_s is not None

    @property
    def pupil_pilot(self) -> bool:
        """Whether the "auto" pupil is tried before the stages, from a pilot at Δn = 0 (the first phase;
        :mod:`napari_fdt.recon.choices.parts_pilot`)."""
        return any(p.pass_name == PUPIL_PILOT for p in self.phases)

    @property
    def iterations(self) -> int:
        return sum(p.iterations for p in self.phases)

    @property
    def predicted_s(self) -> float:
        return sum(p.predicted_s for p in self.phases)

    def index(self, pass_name: str, stage: int, trials: bool = False) -> int:
        """The index of the phase of ``pass_name`` at ``stage`` (``trials``: the TV trials); the last one where the stage
        runs again more than once (the finest stage again with sub-slices, then every stage again)."""
        for i in reversed(range(len(self.phases))):
            p = self.phases[i]
            if p.pass_name == pass_name and p.stage == stage and p.trials == trials:
                return i
        raise KeyError(f"no phase {pass_name!r} at stage {stage} (trials {trials}) in the plan")

    def iterations_before(self, index: int) -> int:
        """Iterations of the phases before phase ``index``."""
        return sum(p.iterations for p in self.phases[:index])

    def with_phase(self, index: int, phase: Phase) -> "Plan":
        """The plan with phase ``index`` replaced by ``phase``."""
        return replace(self, phases=self.phases[:index] + (phase,) + self.phases[index + 1:])

    def with_iterations(self, index: int, iterations: int) -> "Plan":
        """The plan with phase ``index`` cut to ``iterations`` (the TV trials that ended early)."""
        return self.with_phase(index, replace(self.phases[index], iterations=int(iterations)))

    def has(self, pass_name: str, stage: int, trials: bool = False) -> bool:
        """Whether the plan holds the phase of ``pass_name`` at ``stage``."""
        return any(p.pass_name == pass_name and p.stage == stage and p.trials == trials for p in self.phases)

    def with_stages_again(self, stage: int) -> "Plan":
        """The plan when the TV choice at ``stage`` changes what the stages before it did (a weight larger than the one
        they ran with won): they run again with it (the run's phases of those stages, priced as the phases before the
        trials), and ``stage`` runs in full instead of going on after the winner's probe. The plan without this is
        the one where the stages before are kept (:func:`make_plan`)."""
        before = [replace(p, pass_name=RUN) for p in self.phases if p.pass_name == TV_CHOICE and not p.trials and p.stage < stage]
        phases = []
        for p in self.phases:
            if p.pass_name == RUN and p.stage == stage and p.first_iteration > 0:
                phases += before
                p = replace(p, iterations=p.iterations + p.first_iteration, first_iteration=0)
            phases.append(p)
        return replace(self, phases=tuple(phases)).tv_chosen()

    def tv_chosen(self) -> "Plan":
        """The plan once the TV weight is chosen: its share of :attr:`most_extra_s` settled."""
        extra = None if self.most_extra_s is None else self.most_extra_s - self.tv_again_s
        return replace(self, most_extra_s=extra if extra is not None and extra > 1e-9 else None, tv_again_s=0.0)

    def choices_made(self) -> "Plan":
        """The plan once nothing is left to choose that could add work (the model parts' choice kept nothing)."""
        return replace(self, most_extra_s=None, tv_again_s=0.0)

    def without(self, index: int) -> "Plan":
        """The plan without phase ``index`` (a phase that will not run: the first pass's finest stage when a part is
        kept at the last coarse stage's end)."""
        return replace(self, phases=self.phases[:index] + self.phases[index + 1:], if_part_kept_early_s=None, early_test_stage=None)

    def with_rerun(self, reruns: Sequence[Phase], choice_to_come: bool = False, tests_s: float | None = None) -> "Plan":
        """The plan with the phases of the stages run again appended (their ``pass_name`` set to "rerun"); without
        ``choice_to_come`` no choice of parts is to come (and nothing more to price for one); ``tests_s``: the parts
        still to choose are tested again at the last rerun phase's end, for that many seconds
        (:func:`~napari_fdt.recon.choices.parts_switch.tests_again_s`), where the plan priced the first pass's tests."""
        phases = self.phases + tuple(replace(p, pass_name=RERUN) for p in reruns)
        if tests_s is not None and reruns and any(p.test == PARTS_TEST for p in self.phases):
            phases = phases[:-1] + (replace(phases[-1], test_s=tests_s, test=PARTS_TEST),)
        if choice_to_come:
            return replace(self, phases=phases, if_finest_parts_kept_s=None, finest_parts=(), if_part_kept_early_s=None,
                           early_test_stage=None, if_spectral_kept_s=None, if_grid_kept_s=None, most_extra_s=None,
                           tv_again_s=0.0)
        return Plan(phases, self.device_type, half_sets_s=self.half_sets_s, if_part_dropped_s=self.if_part_dropped_s,
                    bounds_s=self.bounds_s)

    def to_dict(self) -> dict[str, Any]:
        return {"device": self.device_type, "phases": [p.to_dict() for p in self.phases],
                "iterations": self.iterations, "predicted_total_s": self.predicted_s,
                "predicted_extra_s_if_a_part_is_kept": self.if_part_kept_s,
                "predicted_extra_s_if_a_part_is_kept_before_the_finest_stage": self.if_part_kept_early_s,
                "predicted_extra_s_if_finest_parts_are_kept": self.if_finest_parts_kept_s, "finest_parts": list(self.finest_parts),
                "pupil_pilot": self.pupil_pilot, "predicted_extra_s_if_a_part_is_dropped_at_the_end": self.if_part_dropped_s,
                "predicted_extra_s_half_set_resolution": self.half_sets_s, "predicted_extra_s_error_bounds": self.bounds_s,
                "predicted_extra_s_if_the_spectral_model_is_kept": self.if_spectral_kept_s,
                "predicted_extra_s_if_the_field_grid_is_kept": self.if_grid_kept_s,
                "predicted_total_s_if_the_costliest_parts_are_kept": self.most_s}

    def summary(self) -> str:
        """One line per phase with its iterations and predicted seconds, and the total."""
        lines = [f"  {p.name}: {p.iterations} it, ~{seconds_in_words(p.predicted_s)}"
                 + (f" (of which ~{seconds_in_words(p.test_s)} {p.test} at its end)" if p.test_s else "") for p in self.phases]
        if self.if_part_kept_s:
            early = ""
            if self.if_part_kept_early_s is not None:
                p = next(q for q in self.phases if q.stage == self.early_test_stage)
                early = (f" (~{seconds_in_words(self.if_part_kept_early_s)} where stage {p.stage + 1}/{p.n_stages}'s end finds it:"
                         " the finest stage then runs once)")
            spectral = (f"; ~{seconds_in_words(self.if_spectral_kept_s)} more if it is the spectral model, a pass per wavelength"
                        + (f" (the 2x field grid tried first in its place: the finest stage again on it, ~{seconds_in_words(self.if_grid_kept_s)}"
                           " more where kept)" if self.if_grid_kept_s else "") if self.if_spectral_kept_s else "")
            lines.append(f"  if the data ask for a model part (pupil, aberrations, ...): every stage again, "
                         f"~{seconds_in_words(self.if_part_kept_s)} more{early}{spectral}")
        if self.if_finest_parts_kept_s:
            what = " or ".join(PART_WORDS.get(p, p) for p in self.finest_parts)
            lines.append(f"  if the data ask for {what} alone: the finest stage again with them, ~{seconds_in_words(self.if_finest_parts_kept_s)} more")
        if self.if_part_dropped_s:
            lines.append(f"  if a kept part no longer helps at the end: the finest stage again without it, ~{seconds_in_words(self.if_part_dropped_s)} more")
        if self.half_sets_s is not None:
            lines.append(f"  then the half-set resolution: each half of the images run again with the run's choices, "
                         f"~{seconds_in_words(self.half_sets_s)} more")
        if self.bounds_s is not None:
            lines.append(f"  then the error bound: the result re-simulated and run again with the run's choices, "
                         f"~{seconds_in_words(self.bounds_s)} more")
        most, top = "", self.range_top_s
        if top is not None:
            most = (f" where the data ask for no model part; up to about {seconds_in_words(top)} where they ask for the"
                    " costliest ones (the lines below)" if self.if_part_kept_s else
                    f"; up to about {seconds_in_words(top)} where a larger TV weight wins (the stages before its trials again)")
        return "\n".join([f"plan ({self.device_type}): {len(self.phases)} phases, {self.iterations} iterations, "
                          f"about {seconds_in_words(self.predicted_s)}{most}", *lines])


def seconds_in_words(s: float) -> str:
    """``s`` seconds as the plan says them: "16 s", "3 min", "1.2 h"."""
    if s < 90:
        return f"{s:.0f} s"
    if s < 5400:
        return f"{s / 60:.0f} min"
    return f"{s / 3600:.1f} h"


def stage_phase(config: SolverConfig, optics: Optics, image_shape: tuple[int, int], sources_um: np.ndarray, stage: int,
                coarse_model: str, device_type: str, pass_name: str = RUN, parts: tuple[str, ...] = (),
                pixel_integration: bool = False, pupil_edge: float | None = None, pilot: bool = False) -> Phase:
    """The phase of stage ``stage`` (its model, FFT grid and predicted seconds per iteration; ``pixel_integration``: the
    multi-slice model's camera integrates over its pixels; ``pupil_edge`` its pupil's edge, None the default; ``parts``
    the kept model parts it runs with: sub-slices and the 2x field grid in the finest stage, obliquity's screens per
    source, the spectral model one pass per wavelength).

    ``pilot``: a step of the pupil's pilot on this stage's model instead (:mod:`napari_fdt.recon.choices.parts_pilot`):
    ``2·PILOT_BATCH`` images at Δn = 0, where the split-field model skips its slice loop (its camera's source field and
    pixel integration remain: on cells_pupil, with pixel integration, the pilot costs 31 finest iterations, on the
    sample 10), plus :data:`PILOT_STEP_OVERHEAD_S` on the CPU."""
    from napari_fdt.recon.problem.stage_spec import CameraModel, stage_spec
    from napari_fdt.recon.problem.stages import config_uses_split_field, model_window, multislice_plan

    sc = config.stages[stage]
    camera = CameraModel(pupil_edge, pixel_integration)
    spec = stage_spec(config, stage, coarse_model, {*parts, *camera.parts_on()}, camera)
    envelope = spec.envelope
    split = False
    if envelope:
        shape = envelope_padded_shape(optics, image_shape, sc.factor)
    else:
        _, opt, _, window = multislice_plan(optics, sc.factor, image_shape, sources_um)
        split = config_uses_split_field(config, device_type, sc.factor, window, opt, pupil_edge, field_grid="field_grid" in parts,
                                        pixel_integration=pixel_integration)
        shape = model_window(window, opt, split)
    model = "envelope" if envelope else "multislice"
    dev = "cuda" if device_type == "cuda" else "cpu"
    batch = 2 * PILOT_BATCH if pilot else config.stage_batch(stage)
    screens = optics.n_slices * spec.screens_per_slice
    if pilot and split:
        screens = 0
    if spec.fine_grid:  # the field on a grid twice as fine
        shape = (2 * shape[0], 2 * shape[1])
    source_pixels = camera_points = 0
    if split:
        from napari_fdt.model.split_field import FINE_MARGIN

        h, w = window.image_shape
        source_pixels = 4 * h * w if spec.fine_grid else h * w  # the sources' field at every screen's (fine) pixels
        camera_points = (2 * h + 2 * FINE_MARGIN) * (2 * w + 2 * FINE_MARGIN) if pixel_integration else h * w
    units = iteration_units(batch, screens, shape, pixel_integration and not envelope, source_pixels, camera_points)
    if split and spec.obliquity == "per_source":  # each source's own screens on the image
        units += float(batch) * screens * source_pixels * OBLIQUITY_UNITS
    if not envelope and ("spectral" in parts or config.coherence in ("spectral", "mask+spectral")):
        units *= config.n_wavelengths  # the spectral model: one forward and backward pass per wavelength
    rate = SECONDS_PER_UNIT[(dev, "split" if split else model)]
    per_it = OVERHEAD_S[dev] + rate * units + (PILOT_STEP_OVERHEAD_S if pilot and dev == "cpu" else 0.0)
    return Phase(pass_name, stage, len(config.stages), sc.factor, model, sc.iterations, shape, per_it, parts=parts)


def make_plan(config: SolverConfig, optics: Optics, image_shape: tuple[int, int], sources_um: np.ndarray,
              coarse_model: str, device_type: str, choose_tv_at: int | None, pixel_integration: bool = False,
              parts_to_choose: bool = False, pupil_edge: float | None = None, finest_parts: tuple[str, ...] = (),
              pupil_pilot: bool = False, early_test_stage: int | None = None, auto_parts: tuple[str, ...] = (),
              n_images: int = 0, n_held: int = 0) -> Plan:
    """The plan of a run of ``config`` (as run: its stages resolved) on ``device_type`` ("cpu" or "cuda"), with the
    initial ``sources_um`` (N, 3) µm, ``coarse_model`` resolved for the device; ``choose_tv_at``: the stage at whose
    start the ``"auto"`` TV weights are tried (None: no choice), every weight for :func:`probe_iterations` of its
    iterations, after the stages before it at the path's smallest weight; then the run's stages from there, the
    selection stage going on after the winner's probe: the plan of the common case, where that smallest weight wins
    (:meth:`Plan.with_stages_again` adds the stages before, run again, where a larger weight wins);
    ``pixel_integration``, ``pupil_edge``: the camera model's (as the first pass runs it); ``parts_to_choose``: "auto" model parts will
    be chosen from the data (:attr:`Plan.if_part_kept_s` then says what keeping one would add); ``finest_parts``: the
    ``"auto"`` parts of the finest stage's model among them (:attr:`Plan.if_finest_parts_kept_s`); ``pupil_pilot``: the
    pupil is tried before the stages (:attr:`Plan.pupil_pilot`); ``early_test_stage``: the stage at whose end the aberrations
    are tested in the first pass (:func:`~napari_fdt.recon.loop.model_parts.coarse_end_test_planned`; None: no such test);
    ``auto_parts``, ``n_images``, ``n_held``: the parts to choose and the images (all, held out) their tests predict,
    priced at the phases' ends where given (:func:`_with_tests`)."""
    src = np.asarray(sources_um, dtype=np.float64)
    stages = [stage_phase(config, optics, image_shape, src, i, coarse_model, device_type, pixel_integration=pixel_integration,
                          pupil_edge=pupil_edge)
              for i in range(len(config.stages))]
    stages_s = sum(p.predicted_s for p in stages)  # the stages as given, before the TV trials reshape them
    phases: list[Phase] = []
    if choose_tv_at is not None:
        probe = probe_iterations(config.stages[choose_tv_at].iterations)
        phases += [replace(p, pass_name=TV_CHOICE) for p in stages[:choose_tv_at]]
        phases.append(replace(stages[choose_tv_at], pass_name=TV_CHOICE, trials=True, iterations=len(TV_PATH) * probe))
        # the selection stage goes on from the winner's trial; the stages before are kept (the smallest weight won)
        stages = stages[choose_tv_at:]
        stages[0] = replace(stages[0], iterations=stages[0].iterations - probe, first_iteration=probe)
    phases += stages
    extra = None
    if parts_to_choose and config.parts_rerun == "stages":
        again = rerun_coarse_model(config.coarse_model, coarse_model)
        extra = sum(stage_phase(config, optics, image_shape, src, i, again, device_type, RERUN,
                                pixel_integration=pixel_integration, pupil_edge=pupil_edge).predicted_s for i in range(len(config.stages)))
    elif parts_to_choose:  # parts_rerun "finest": the finest stage again
        extra = stages[-1].predicted_s
    spectral = None
    if extra is not None and config.parts_rerun == "stages" and "spectral" in auto_parts:  # every stage again, k passes
        spectral = sum(stage_phase(config, optics, image_shape, src, i, again, device_type, RERUN, ("spectral",),
                                   pixel_integration=pixel_integration, pupil_edge=pupil_edge).predicted_s
                       for i in range(len(config.stages)))
    early = None
    if extra is not None and config.parts_rerun == "stages" and early_test_stage is not None:
        early = extra - stages[-1].predicted_s  # found at the coarse stage's end: the first pass's finest stage never runs
    finest_again, finest_parts = None, tuple(finest_parts) if parts_to_choose else ()
    if grid_waits_for_spectral(config, auto_parts):  # the grid comes with a spectral model's keep, priced there
        finest_parts = tuple(p for p in finest_parts if p != "field_grid")
    if finest_parts:
        last = len(config.stages) - 1
        finest_again = stage_phase(config, optics, image_shape, src, last, coarse_model, device_type, RERUN, finest_parts,
                                   pixel_integration=pixel_integration, pupil_edge=pupil_edge).predicted_s
    if pupil_pilot:  # first, the pupil's pilot: steps of 2·PILOT_BATCH images through the finest stage's model at Δn = 0
        pilot = stage_phase(config, optics, image_shape, src, len(config.stages) - 1, coarse_model, device_type,
                            pixel_integration=pixel_integration, pupil_edge=pupil_edge, pilot=True)
        phases.insert(0, replace(pilot, pass_name=PUPIL_PILOT, iterations=PILOT_ITERATIONS, first_iteration=0))
    halves = None
    if config.half_set_resolution:  # the stages of each half (as given; the finest stage may run shorter on fewer images)
        from napari_fdt.recon.assess.validation import split_halves

        halves = sum(stage_phase(config, optics, image_shape, src[idx], i, coarse_model, device_type, pixel_integration=pixel_integration,
                                 pupil_edge=pupil_edge).predicted_s
                     for idx in split_halves(src, config.seed) for i in range(len(config.stages)))
    bounds = None
    if config.error_bounds:  # the stages again per replicate, as given (the parts the run keeps are not known yet)
        from napari_fdt.recon.assess.bounds import REPLICATES

        bounds = REPLICATES * stages_s
    dropped = stages[-1].predicted_s if parts_to_choose and config.parts_backward else None
    if parts_to_choose and n_images:
        phases, grid_first_s = _with_tests(phases, config, optics, image_shape, src, coarse_model, device_type, pixel_integration,
                                           pupil_edge, auto_parts, n_images, n_held, early)
        if spectral is not None:  # under "before_spectral" the 2x grid is tested before a spectral model is kept
            spectral += grid_first_s
    grid_kept = None
    if spectral is not None and grid_waits_for_spectral(config, auto_parts):  # the finest stage again on the grid
        with_grid = ("field_grid", "sub_slices") if "sub_slices" in auto_parts else ("field_grid",)
        grid_kept = stage_phase(config, optics, image_shape, src, len(config.stages) - 1, coarse_model, device_type, RERUN,
                                with_grid, pixel_integration=pixel_integration, pupil_edge=pupil_edge).predicted_s
    plan = Plan(tuple(phases), "cuda" if device_type == "cuda" else "cpu", extra, early, early_test_stage if early is not None else None,
                finest_again, finest_parts, dropped, halves, bounds, spectral, if_grid_kept_s=grid_kept)
    # a TV weight larger than the one the stages before the trials ran with: they run again with it
    tv_again_s = plan.with_stages_again(choose_tv_at).predicted_s - plan.predicted_s if choose_tv_at is not None else 0.0
    if extra is None:
        return replace(plan, most_extra_s=tv_again_s, tv_again_s=tv_again_s) if choose_tv_at is not None else plan
    # the run's choices chained (every stage again with a part of the stages' model, the finest stage's parts kept with
    # it; then the finest stage again with its own parts; then a drop at the end), each chain with its costliest parts:
    # a fitted part (priced as the stages as given), obliquity's screens, the camera's pixel means; the spectral model
    # (its passes; where the 2x grid is tried in its place, the grid's keep is a chain of the finest stage's parts)
    again_s = [extra]
    if config.parts_rerun == "stages":
        for part in (None, *(p for p in ("obliquity", "pixel_integration") if p in auto_parts)):
            parts = (part, *finest_parts) if part else finest_parts
            again_s.append(sum(stage_phase(config, optics, image_shape, src, i, again, device_type, RERUN, parts,
                                           pixel_integration=pixel_integration or part == "pixel_integration",
                                           pupil_edge=pupil_edge).predicted_s for i in range(len(config.stages))))
    finest_s = max(finest_again or 0.0, grid_kept or 0.0)
    backward = bool(config.parts_backward)
    most = max(most_seconds(plan, max(again_s), finest_s, backward), most_seconds(plan, 0.0, finest_s, backward))
    if spectral is not None:  # the spectral model's passes, then the finest stage's parts other than a grid it excludes
        most = max(most, most_seconds(plan, spectral, (finest_again or 0.0) if grid_kept is not None else finest_s, backward))
    return replace(plan, most_extra_s=most + tv_again_s - plan.predicted_s, tv_again_s=tv_again_s)


def most_seconds(plan: Plan, again_s: float, finest_s: float, backward: bool) -> float:
    """The run's seconds where the data ask for the costliest model parts of each kind, as the run's choices chain
    them: ``plan``'s phases; every stage again (``again_s``, 0 where no part of the stages' model is kept) with the
    finest stage's tests again (priced as the first pass's); the finest stage again with its costliest parts
    (``finest_s``, 0 where none is to choose: sub-slices, the 2x grid); and, with ``backward``, once more at the end
    where a kept part is dropped (priced as the larger of the finest stage with those parts and as given). Not a bound:
    two parts of the stages' model kept together, or kept parts dearer than priced, cost more."""
    tests_s = sum(p.test_s for p in plan.phases if p.test == PARTS_TEST) if again_s else 0.0
    finest = max(p.iterations_s for p in plan.phases if p.pass_name == RUN and p.stage == p.n_stages - 1)
    return plan.predicted_s + again_s + tests_s + finest_s + (max(finest_s, finest) if backward else 0.0)


def _with_tests(phases: list[Phase], config: SolverConfig, optics: Optics, image_shape: tuple[int, int], src: np.ndarray,
                coarse_model: str, device_type: str, pixel_integration: bool, pupil_edge: float | None,
                auto_parts: tuple[str, ...], n_images: int, n_held: int, early: float | None) -> tuple[list[Phase], float]:
    """``phases`` with the model parts' tests priced at the ends of the phases they follow: the finest stage's first run,
    and the last coarse stage's (where ``early``, that test's price of a keep, is planned); and the seconds of the 2x
    grid's test where ``field_oversampling`` is ``"before_spectral"`` (tested only before a spectral model is kept: not
    in the finest stage's price), else 0."""
    from napari_fdt.recon.loop.model_parts import coarse_test_stage
    from napari_fdt.recon.loop.parts_price import coarse_end_test_s, finest_end_test_s, finest_test_setup, part_costs

    last, dev = len(config.stages) - 1, ("cuda" if device_type == "cuda" else "cpu")
    batch = config.stage_batch(last)

    def image_s(parts: tuple[str, ...]) -> float:
        return stage_phase(config, optics, image_shape, src, last, coarse_model, device_type, RUN, parts,
                           pixel_integration=pixel_integration, pupil_edge=pupil_edge).seconds_per_iteration / batch

    n_test, n_fit, branch = finest_test_setup(config, n_images, n_held)
    out = list(phases)
    finest = max(i for i, p in enumerate(out) if p.pass_name == RUN and p.stage == last)
    costs = part_costs(out[finest].seconds_per_iteration / batch, image_s, auto_parts)
    grid_later = grid_waits_for_spectral(config, auto_parts)
    tested = tuple(p for p in auto_parts if not (grid_later and p == "field_grid"))
    test_s = finest_end_test_s(costs, tested, n_test, n_fit, n_held, dev, branch)
    grid_s = finest_end_test_s(costs, tested + ("field_grid",), n_test, n_fit, n_held, dev, branch) - test_s if grid_later else 0.0
    out[finest] = replace(out[finest], test_s=test_s, test=PARTS_TEST)
    stage = coarse_test_stage(config)
    runs = [i for i, p in enumerate(out) if p.pass_name == RUN and p.stage == stage]
    if early is not None and runs:
        out[runs[-1]] = replace(out[runs[-1]], test_s=coarse_end_test_s(costs[""], n_test, n_fit, dev), test="testing the aberrations")
    return out, grid_s


def plan_for(acquisition, config: SolverConfig, device_type: str, sources_um: np.ndarray | None = None) -> tuple[Plan, np.ndarray]:
    """The plan a reconstruction of ``acquisition`` with ``config`` would run on ``device_type``, before anything is
    allocated (as :class:`~napari_fdt.recon.run.solver.Reconstructor` makes it), and the initial sources (N, 3) µm it used:
    ``sources_um``, else the acquisition's, else the 2D-Gaussian fit of the images (a few seconds)."""
    from napari_fdt.recon.assess.validation import holdout_indices
    from napari_fdt.recon.loop.regularisation import tv_is_auto
    from napari_fdt.recon.problem.stages import camera_model
    from napari_fdt.recon.settings.config import resolve_coarse_model, resolve_stage_lengths

    cfg = resolve_stage_lengths(config, acquisition.n_images)
    if sources_um is None:
        sources_um = acquisition.sources_um
    if sources_um is None:
        from napari_fdt.recon.calibration.source_fit import initial_sources

        sources_um, _ = initial_sources(acquisition, depth_um=cfg.source_depth_um, device="cpu")
    src = np.asarray(sources_um, dtype=np.float64)
    n_held = len(holdout_indices(src, cfg.validation_fraction))
    split = n_held > 0
    choose_tv_at = min(selection_stages(cfg)) if tv_is_auto(cfg) and split else None
    from napari_fdt.recon.loop.model_parts import FINEST_ONLY_PARTS, coarse_end_test_planned, coarse_test_stage, pupil_pilot_wanted, requested_for

    # the parts as the run starts them; pixel integration as stated, else the physical rule
    coarse_model = resolve_coarse_model(cfg.coarse_model, device_type)
    requested, _ = requested_for(cfg, acquisition, coarse_model)

    early = coarse_test_stage(cfg) if coarse_end_test_planned(cfg, n_held, requested["aberrations"] is None) else None
    plan = make_plan(cfg, acquisition.optics, acquisition.image_shape, src, coarse_model,
                     device_type, choose_tv_at, pixel_integration=requested["pixel_integration"],
                     parts_to_choose=split and any(v is None for v in requested.values()),
                     pupil_edge=camera_model(cfg, acquisition).pupil_edge,
                     finest_parts=tuple(p for p in FINEST_ONLY_PARTS if requested[p] is None),
                     pupil_pilot=pupil_pilot_wanted(cfg, n_held, requested["pupil"] is None), early_test_stage=early,
                     auto_parts=tuple(p for p, v in requested.items() if v is None), n_images=len(src), n_held=n_held)
    return plan, src
