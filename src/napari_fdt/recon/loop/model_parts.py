"""Optional parts of the model, switched on where the data shows they matter (issue 13, ``docs/solver.md``).

The parts: sub-slices in the finest stage (``sub_slices``: diffraction inside thick slices; tried only where the
slices are at least half the depth of field, :func:`~napari_fdt.recon.problem.stages.thick_slices`), the finest stage's field
on a grid twice as fine as the camera's (``field_oversampling``, part ``field_grid``: tried only where the camera grid
aliases waves the medium carries, :func:`~napari_fdt.recon.problem.stages.camera_grid_drops_band`), the camera's pixel
integration (``pixel_integration``), the thin screen's obliquity correction (``obliquity_correction``), the spectral
model of the emission band (``coherence``), a fit of the pupil's NA and edge (``calibrate_pupil``) and a fit of
low-order aberrations (``calibrate_aberrations``). Each setting is ``true``, ``false`` or ``"auto"`` (the default; for
``coherence`` the other values are the coherence models, for ``sub_slices`` and ``field_oversampling`` numbers).

How "auto" chooses (:func:`napari_fdt.recon.choices.parts_search.choose_parts`), once, at the end of the finest stage (the
full multi-slice model, and a volume holding the stage's detail: earlier, the held-out images' error is mostly the
coarse volume's and hides what the model lacks; :mod:`napari_fdt.recon.choices.plugged` says what runs again):

1. The reference is the model with the auto parts off: the validation error of each held-out image
   (:mod:`napari_fdt.recon.assess.validation`; positions as fitted to their own images, gains in closed form).
2. The parts without parameters (sub-slices, field grid, pixel integration, obliquity, spectral), one at a time: the held-out images are
   predicted with the part on, through the same volume. Sub-slices or the field grid rejected there are tried again by a
   short branch of training with and without them (:mod:`napari_fdt.recon.choices.parts_branch`); kept so, every stage
   runs again with them and the parts not yet tried wait for that pass.
3. The parts with parameters (pupil, aberrations), one at a time on top of what step 2 kept: their parameters are fitted
   to a subset of the *training* images with the volume and sources held fixed (:data:`FIT_ITERATIONS` Adam steps on
   the images' relative error with closed-form gains; the field leaving the volume is computed once, the pupil is
   the only thing recomputed), then the held-out images are predicted with the fitted values. Two kept parts are
   refitted together.
4. A part is kept when it explains the held-out images better by more than noise would: the paired improvement
   ``d_i = e_i(reference) − e_i(part)`` has a mean above Student's t quantile (:func:`standard_errors`) times its
   standard error and above :data:`MIN_IMPROVEMENT` of the reference error (:func:`decide`). The kept part becomes the reference of the
   next one.

The finest stage then goes on with the kept parts, from the fitted values. The volume the parts are judged with was
trained without them, so the test is conservative: a part must show through a volume that may have absorbed some of
its effect. Without a validation split the auto parts are off. (Pixel integration is not chosen here: where the files
do not state it, the physical rule of :func:`napari_fdt.physics.camera.needs_pixel_integration` sets it,
:func:`requested_for`.)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from napari_fdt.recon.problem.stage_spec import runs_envelope
from napari_fdt.recon.problem.stages import camera_grid_drops_band, resolved_pixel_integration, stated_pixel_integration, thick_slices
from napari_fdt.recon.settings.config import AUTO, BEFORE_SPECTRAL, SolverConfig, grid_to_choose

__all__ = ["PARTS", "BINARY_PARTS", "FITTED_PARTS", "SETTING_OF", "STANDARD_ERRORS_LEVEL", "standard_errors", "MIN_IMPROVEMENT", "FIT_ITERATIONS",
           "FIT_IMAGES", "FIT_RATES", "PILOT_ITERATIONS", "PILOT_BATCH",
           "FINEST_ONLY_PARTS", "BRANCH_SHARE", "BRANCH_MIN_ITERATIONS", "branch_iterations", "PartsChoice", "EarlyTrials",
           "pupil_pilot_wanted", "decide", "switch", "requested_parts", "requested_for", "parts_stage",
           "coarse_test_stage", "coarse_end_test_planned"]

#: Parts without parameters, tried first, in this order (sub-slices first: a spectral model or a pupil fit can absorb
#: part of a thin screen's error, as the spectral model did on beads simulated with sub-slices, docs/benchmarks.md).
BINARY_PARTS: tuple[str, ...] = ("sub_slices", "field_grid", "pixel_integration", "obliquity", "spectral")
#: Parts with fitted parameters, tried on top of the kept binary parts.
FITTED_PARTS: tuple[str, ...] = ("pupil", "aberrations")
PARTS: tuple[str, ...] = BINARY_PARTS + FITTED_PARTS
#: The setting of each part.
SETTING_OF: dict[str, str] = {"sub_slices": "sub_slices", "field_grid": "field_oversampling",
                              "pixel_integration": "pixel_integration", "obliquity": "obliquity_correction", "spectral": "coherence",
                              "pupil": "calibrate_pupil", "aberrations": "calibrate_aberrations"}
#: One-sided false-positive rate of the test per part: the mean paired improvement must exceed Student's t quantile
#: ``t(1 − STANDARD_ERRORS_LEVEL, n − 1)`` standard errors of that mean (n held-out images; 1.96 for many images, 2.57
#: for 6, 4.30 for 3: with few images the standard error itself is uncertain).
STANDARD_ERRORS_LEVEL = 0.025
#: t(0.975, df) for df = 1 … 30 (above: the normal quantile 1.96).
_T975 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145, 2.131,
         2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042)


def standard_errors(n_images: int) -> float:
    """Standard errors a mean paired improvement over ``n_images`` (≥ 2) must exceed: Student's t(0.975, n − 1)."""
    df = n_images - 1
    return _T975[df - 1] if df <= len(_T975) else 1.96
#: Smallest mean improvement that counts, relative to the reference's validation error: below it a part's gain is
#: not worth its cost whatever its significance.
MIN_IMPROVEMENT = 0.01
#: The same floor for the aberrations tested at the last coarse stage's end
#: (:mod:`napari_fdt.recon.choices.parts_coarse_end`). Through a coarse volume a Zernike fit also absorbs misfit the volume
#: still has: on the sample (no aberration) the fit improved the test images by 0.72, 0.83 and 1.06 % at seeds 0-2
#: (z 3.1-4.7), on the tests' 32² scene after 10 coarse iterations by 2.25 %; where the images have 0.5 rad of spherical
#: aberration by 4.3-5.2 % (beads_real, letters_real, seeds 0 and 1; z 9.2-10.1). A part this test misses is tried again
#: at the finest stage's end.
COARSE_END_MIN_IMPROVEMENT = 0.03
#: Parts that change only the finest stage's model (not the coarse stages'): where the choice keeps only these, the finest
#: stage runs again from its start with them (the stages before it would run as they did), whatever ``parts_rerun`` says.
FINEST_ONLY_PARTS: tuple[str, ...] = ("sub_slices", "field_grid")
#: The branch trial's iterations (:mod:`napari_fdt.recon.choices.parts_branch`) as a share of the finest stage's.
#: Measured from the finest stage's end at seed 0 with 8 iterations (5 % of 160): sub-slices lowered the held-out error
#: of beads_high (made with 4 screens per slice) by 14.5 % (z 10.6) and raised that of beads (made with one screen per
#: slice) by 8.4 % (z −10.0); with 16 iterations 15.7 % and −6.7 % (docs/decisions/parts-backward.md).
BRANCH_SHARE = 0.05
#: The fewest iterations of a branch.
BRANCH_MIN_ITERATIONS = 4


def branch_iterations(finest_iterations: int) -> int:
    """Iterations of each arm of a branch trial at the end of a finest stage of ``finest_iterations``."""
    return max(BRANCH_MIN_ITERATIONS, int(round(BRANCH_SHARE * finest_iterations)))


#: Adam steps of the fit of a part's parameters with the volume fixed.
FIT_ITERATIONS = 30
#: Training images the parameters are fitted to (evenly spread over the training images).
FIT_IMAGES = 8
#: Training images the 2x field grid's trial predicts at most, besides the held-out ones (evenly spread): its model
#: costs about 4x a camera-grid prediction on the full window (37 s of a 213 s run on letters128 with every image).
GRID_TRIAL_TRAINING_IMAGES = 32
#: Adam step sizes of the fit: Zernike coefficients (rad), NA scale (relative), pupil edge (relative to NA/λ).
FIT_RATES: dict[str, float] = {"zernike": 0.05, "na_scale": 0.003, "pupil_edge": 0.005}
#: The pupil pilot before the stages (:mod:`napari_fdt.recon.choices.parts_pilot`): its steps, and the images of each kind
#: (fit images, held-out images) per step. On cells_pupil the test kept the pupil after 60 such steps but not after 80
#: steps over the whole training set: the test needs the positions of its own images converged.
PILOT_ITERATIONS = 60
PILOT_BATCH = 8


def switch(value: Any) -> bool | None:
    """A part's setting as True / False, or None for ``"auto"`` (booleans and ``"true"``/``"false"`` accepted)."""
    if value == AUTO:
        return None
    if isinstance(value, str):
        return value == "true"
    return bool(value)


def requested_parts(config: SolverConfig) -> dict[str, bool | None]:
    """Each part's setting: True / False when given, None when ``"auto"`` (before what the acquisition states:
    ``pixel_integration`` stated by ``acquisition.json`` is resolved by the caller)."""
    out = {part: switch(getattr(config, SETTING_OF[part])) for part in PARTS if part not in ("spectral", "sub_slices", "field_grid")}
    out["sub_slices"] = None if config.sub_slices == AUTO else config.sub_slices > 1
    out["field_grid"] = None if grid_to_choose(config.field_oversampling) else config.field_oversampling == 2
    coherence = config.coherence
    out["spectral"] = None if coherence == AUTO else coherence in ("spectral", "mask+spectral")
    return {part: out[part] for part in PARTS}


def grid_waits_for_spectral(config: SolverConfig, auto_parts: tuple[str, ...] | list[str]) -> bool:
    """Whether the 2x field grid (part ``field_grid``, among ``auto_parts``) is tried only where a spectral model passes
    its trial, before that model is kept (``field_oversampling = "before_spectral"``): not in the finest stage's tests
    of its own, and priced with the spectral model's keep. The one place the search, the plan and its words ask."""
    return "field_grid" in auto_parts and config.field_oversampling == BEFORE_SPECTRAL


def pupil_pilot_wanted(config: SolverConfig, n_held_out: int, pupil_auto: bool) -> bool:
    """Whether the pupil is tried before the stages (:mod:`napari_fdt.recon.choices.parts_pilot`): ``parts_pilot`` on, the pupil
    ``"auto"`` and at least two images held out (the paired test's noise estimate). The plan of ``fdt plan`` and the
    solver's both read it."""
    return bool(config.parts_pilot) and pupil_auto and n_held_out >= 2


def parts_stage(config: SolverConfig) -> int:
    """The stage at whose start the auto parts are chosen: the last stage with iterations (the finest)."""
    with_iterations = [i for i, s in enumerate(config.stages) if s.iterations > 0]
    return with_iterations[-1] if with_iterations else len(config.stages) - 1


def next_pass(trials: list[dict[str, Any]]) -> int:
    """The number of the pass whose trials come next: one more than the last pass's, where the trials at a coarse
    stage's end of a pass run again (``at_stage``, pass > 1) share the number of the pass whose finest stage follows
    them (the pilot's trials are pass 0, a first pass's 1)."""
    return 1 + max((t.get("pass", 1) for t in trials if not ("at_stage" in t and t.get("pass", 1) > 1)), default=1)


def decide(reference: list[float] | np.ndarray, candidate: list[float] | np.ndarray, *,
           min_improvement: float = MIN_IMPROVEMENT) -> dict[str, Any]:
    """Whether a part's per-image validation errors ``candidate`` beat ``reference`` (the same images) by more than noise.

    Returns ``{"on", "improvement", "standard_error", "threshold"}``: the mean of ``reference − candidate``, its
    standard error (sample standard deviation / √n), the t quantile :func:`standard_errors` (n), and ``on`` = mean >
    threshold·SE and mean > ``min_improvement``·mean reference (a one-sided paired t-test at
    :data:`STANDARD_ERRORS_LEVEL`, and a floor). With fewer than two images, no part is switched on (no noise estimate).
    """
    ref = np.asarray(reference, dtype=np.float64)
    cand = np.asarray(candidate, dtype=np.float64)
    if ref.shape != cand.shape:
        raise ValueError(f"reference and candidate must hold the same images, got {ref.shape} and {cand.shape}")
    if ref.size < 2:
        return {"on": False, "improvement": float(ref.mean() - cand.mean()) if ref.size else 0.0, "standard_error": float("nan")}
    d = ref - cand
    mean, se = float(d.mean()), float(d.std(ddof=1) / np.sqrt(d.size))
    t = standard_errors(d.size)
    on = mean > t * se and mean > min_improvement * float(ref.mean())
    return {"on": bool(on), "improvement": mean, "standard_error": se, "threshold": t}


@dataclass
class PartsChoice:
    """What the automatic choice of model parts tried and chose (RI.json's ``model_parts``).

    ``parts``: every part's final switch; ``chosen_by``: per part ``"setting"``, ``"acquisition"`` (stated by
    ``acquisition.json``), ``"validation"`` (tried) or ``"no validation split"``; ``trials``: per tried part its
    validation error, per-image errors, improvement and standard error, fitted values and seconds; ``fitted``: the
    values the finest stage starts from (``zernike_rad`` per mode, ``na``, ``pupil_edge``); ``seconds``: the cost of
    the choice; ``stage``, ``iteration``: where it was made (after that many iterations of the stage); ``rerun`` and
    ``pending``: see the fields (a choice that ran every stage again holds both passes' trials, each with its ``pass``).
    """

    parts: dict[str, bool]
    chosen_by: dict[str, str]
    stage: int = -1
    iteration: int = 0
    reference_error: float | None = None
    reference_image_errors: list[float] = field(default_factory=list)
    trials: list[dict[str, Any]] = field(default_factory=list)
    fitted: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0
    #: ``"stages"`` when the choice kept a part and every stage ran again with it (``parts_rerun``); ``"finest"`` when it
    #: kept only parts of the finest stage's model and that stage ran again with them (:data:`FINEST_ONLY_PARTS`); else None
    rerun: str | None = None
    #: the auto parts the finest stage of that second pass chooses again (empty once chosen)
    pending: list[str] = field(default_factory=list)
    #: the backward step at the end (:mod:`napari_fdt.recon.choices.parts_backward`): each kept part's effect in the final
    #: state, the parts dropped, and the finest stage's rerun without them; None before (or without kept parts)
    backward: dict[str, Any] | None = None

    @property
    def needed(self) -> list[str]:
        """The parts on."""
        return [p for p in PARTS if self.parts.get(p)]

    def to_dict(self) -> dict[str, Any]:
        return {"parts": dict(self.parts), "chosen_by": dict(self.chosen_by), "stage": self.stage, "iteration": self.iteration, "reference_error": self.reference_error,
                "reference_image_errors": list(self.reference_image_errors), "trials": list(self.trials), "fitted": dict(self.fitted),
                "seconds": self.seconds, "needed": self.needed, "rerun": self.rerun, "pending": list(self.pending),
                "backward": self.backward}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "PartsChoice":
        # a choice saved before a part existed: that part off, as the run had it
        parts = {**{p: False for p in PARTS}, **d["parts"]}
        chosen_by = {**{p: "setting" for p in PARTS}, **d["chosen_by"]}
        return cls(parts=parts, chosen_by=chosen_by, stage=int(d.get("stage", -1)), iteration=int(d.get("iteration", 0)),
                   reference_error=d.get("reference_error"), reference_image_errors=list(d.get("reference_image_errors", [])),
                   trials=list(d.get("trials", [])), fitted=dict(d.get("fitted", {})), seconds=float(d.get("seconds", 0.0)),
                   rerun=d.get("rerun"), pending=list(d.get("pending", [])), backward=d.get("backward"))


@dataclass
class EarlyTrials:
    """Trials of ``"auto"`` parts made before the finest stage's choice that kept nothing: the pupil's pilot at Δn = 0
    (``"pass": 0``) and the last coarse stage's end (``"pass": 1``, ``"at_stage"``). The finest stage's choice lists
    them first (RI.json's ``model_parts.trials``); ``seconds``: what they took. Saved in checkpoints with the run's state."""

    trials: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {"trials": list(self.trials), "seconds": self.seconds}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "EarlyTrials":
        return cls(list(d.get("trials", [])), float(d.get("seconds", 0.0)))

def requested_for(cfg, acquisition, coarse_model: str | None = None) -> tuple[dict[str, bool | None], dict[str, str]]:
    """Each part as the settings and the acquisition ask for it (None: "auto", to choose from the data), and why.

    ``coarse_model``: the run's coarse model resolved for its device; where the stage the parts are chosen at (the
    finest with iterations) is coarser than the camera's grid and runs the envelope model, which holds none of the
    parts, every "auto" part is off (a schedule that ends at x2: nothing to test them through)."""
    requested = requested_parts(cfg)
    chosen_by = {p: "setting" for p in PARTS}
    if coarse_model is not None:
        factor = cfg.stages[parts_stage(cfg)].factor
        if runs_envelope(factor, coarse_model):
            for p in PARTS:
                if requested[p] is None:
                    requested[p] = False
                    chosen_by[p] = f"the finest stage (x{factor}) runs the envelope model, which holds no model part"
    stated = stated_pixel_integration(cfg, acquisition)
    if cfg.pixel_integration == "auto" and stated is not None:
        chosen_by["pixel_integration"] = "acquisition"
    elif stated is None:
        # a real camera's files that do not say: every camera integrates over its pixels, and the physical rule says
        # where that shows in the images. The data cannot choose it: at Δn = 0 the sources' smooth light does not show
        # it (the pilot), and at the finest stage's end, through a volume trained without it, it made the held-out
        # images worse on cells_pupil's images (+3.5 %) that have it (docs/decisions/model-parts.md)
        stated = resolved_pixel_integration(cfg, acquisition)
        chosen_by["pixel_integration"] = "physics: " + ("the intensity's band 2·NA/λ exceeds the camera's Nyquist" if stated
                                                        else "the camera's Nyquist holds the intensity's band 2·NA/λ")
    requested["pixel_integration"] = stated
    if requested["sub_slices"] is None and not thick_slices(acquisition.optics):
        # the physics' criterion: slices thin against the depth of field are thin screens, no trial needed
        requested["sub_slices"] = False
        chosen_by["sub_slices"] = "physics: slices under half the depth of field"
    if requested["field_grid"] is None and not camera_grid_drops_band(acquisition.optics):
        # the physics' criterion: the camera grid holds every wave the medium carries, nothing aliases
        requested["field_grid"] = False
        chosen_by["field_grid"] = "physics: the camera grid holds the medium's band"
    extra = getattr(acquisition, "extra", None) or {}
    if requested["pupil"] is None and "pupil_edge" in extra and cfg.pupil_edge is None:
        # a pupil the acquisition states (as fdt simulate writes it) is taken as stated, like its pixel integration
        requested["pupil"] = False
        chosen_by["pupil"] = "acquisition"
    return requested, chosen_by


def coarse_test_stage(config: SolverConfig) -> int | None:
    """The stage at whose end the aberrations are tested: the last stage with iterations before the finest one and
    coarser than it (None where there is none)."""
    last = parts_stage(config)
    before = [i for i in range(last) if config.stages[i].iterations > 0 and config.stages[i].factor > config.stages[last].factor]
    return before[-1] if before else None


def coarse_end_test_planned(config: SolverConfig, n_held_out: int, parts_to_test: bool) -> bool:
    """Whether a test at :func:`coarse_test_stage`'s end is to run: ``parts_pilot`` on, ``parts_rerun`` ``"stages"``,
    ``parts_to_test`` (in a first pass: the aberrations ``"auto"``), at least two images held out (the test's noise
    estimate), and such a stage (in a distributed run too: each rank predicts and fits on its own images). Known before
    the run (the plan prices what a part kept there adds: :attr:`~napari_fdt.recon.loop.plan.Plan.if_part_kept_early_s`)."""
    return (bool(config.parts_pilot) and config.parts_rerun == "stages" and n_held_out >= 2
            and parts_to_test and coarse_test_stage(config) is not None)
