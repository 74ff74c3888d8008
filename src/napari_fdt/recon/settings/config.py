"""Every solver setting, in one JSON-serialisable configuration shared by the API, ``fdt`` and napari.

The fields below are the schema (:mod:`napari_fdt.schema`): their descriptions, bounds and choices are read by
``fdt reconstruct``'s flags, the napari widgets and the settings table of ``docs/settings.md`` (regenerate it with
``python scripts/settings_table.py --write``). Unknown keys are refused (a typo would otherwise be silently
ignored) and bad values raise :class:`~napari_fdt.errors.FDTInputError` naming the field and the fix.
"""

from __future__ import annotations

import dataclasses
import json
import math
import typing
import warnings
from dataclasses import asdict
from pathlib import Path
from typing import Any, Literal, Optional

from pydantic import BeforeValidator, Field, model_validator

from napari_fdt.errors import FDTInputError, FDTWarning
from napari_fdt.schema import markdown_table, schema_dataclass, setting

__all__ = ["StageConfig", "SolverConfig", "AutoWeight", "AUTO", "BEFORE_SPECTRAL", "grid_to_choose", "load_config", "COHERENCE_MODELS", "BACKWARD_MODES", "COARSE_MODELS",
           "resolve_coarse_model", "settings_markdown"]

#: "auto": the spectral model where the validation error shows it (:mod:`napari_fdt.recon.loop.model_parts`), else none.
CoherenceModel = Literal["auto", "none", "mask", "spectral", "mask+spectral"]
#: Model of the coarse stages; "auto": the envelope model on a CPU (12× cheaper than multi-slice there),
#: multi-slice on a GPU (where the envelope model's many small kernels made it slower; docs/benchmarks.md).
CoarseModel = Literal["auto", "envelope", "multislice"]
#: Window of the multi-slice model's fields (``field_window``).
FieldWindow = Literal["auto", "full", "split"]
#: Values of a setting that were removed, still read from older settings files and reports (RI.json):
#: (setting, value) → (the value used instead, why it went). Loading one gives an :class:`FDTWarning`.
REMOVED_VALUES: dict[tuple[str, str], tuple[str, str]] = {
    ("backward_mode", "fused"): ("auto", "removed on 2026-11-26: slower than the FFT loop on an H200, "
                                         "docs/decisions/gpu-checklist-h200.md"),
}


def _removed_value(name: str):
    """A before-validator of setting ``name``: a value of :data:`REMOVED_VALUES` becomes its replacement, with a warning."""
    def replace(value: Any) -> Any:
        if isinstance(value, str) and (name, value) in REMOVED_VALUES:
            new, why = REMOVED_VALUES[name, value]
            warnings.warn(f'{name}: "{value}" was {why}; using "{new}"', FDTWarning, stacklevel=2)
            return new
        return value
    return replace


_BackwardModeValues = Literal["auto", "stored", "reversible", "checkpoint", "autograd"]
#: How the multi-slice model forms gradients (:mod:`napari_fdt.model.slice_loop`); "autograd" is the plain reference.
#: "fused" (two Triton kernels per slice) was removed: it reads as "auto", with a warning (:data:`REMOVED_VALUES`).
BackwardMode = typing.Annotated[_BackwardModeValues, BeforeValidator(_removed_value("backward_mode"))]
Activation = Literal["paper", "signed"]
#: What runs again when the choice of model parts keeps a part (:mod:`napari_fdt.recon.loop.model_parts`).
PartsRerun = Literal["stages", "finest"]
#: The images the choice of model parts tests on.
PartsTestImages = Literal["held_out", "held_out+training"]


def _bool_to_text(value: Any) -> Any:
    """JSON ``true``/``false`` (and Python bools) as the strings of the ``Literal``."""
    return ("true" if value else "false") if isinstance(value, bool) else value


#: Pixel integration of the camera: "auto" (the acquisition's statement, else the physical rule), "true", "false"
#: (JSON booleans are accepted and stored as these strings).
PixelIntegration = typing.Annotated[Literal["auto", "true", "false"], BeforeValidator(_bool_to_text)]
#: An optional part of the model: "auto" (chosen by the validation error, :mod:`napari_fdt.recon.loop.model_parts`),
#: "true", "false" (JSON booleans are accepted and stored as these strings).
Switch = typing.Annotated[Literal["auto", "true", "false"], BeforeValidator(_bool_to_text)]
#: What the held-out images' error does to a stage: "best" returns to the stage's iterate of lowest validation error,
#: "stop" also ends the stage once it has risen for ``early_stopping_patience`` snapshots, "off" ignores it.
EarlyStopping = Literal["best", "stop", "off"]
#: How the per-source positions step (:class:`~napari_fdt.recon.calibration.calibration.CalibrationOptimiser`).
SourceStep = Literal["per_visit", "whitened", "dense"]
SourceStepSchedule = Literal["constant", "cosine"]
#: A regularisation weight: a number ≥ 0, or ``"auto"``: chosen from the data by the validation error
#: (:mod:`napari_fdt.recon.loop.regularisation`, ``docs/solver.md``).
AutoWeight = typing.Union[typing.Annotated[float, Field(ge=0, strict=True)], Literal["auto"]]
#: Screens per slice: a whole number 1-16, or ``"auto"``: a model part chosen by the held-out images where the physics
#: says the slices are thick (:mod:`napari_fdt.recon.loop.model_parts`).
SubSlices = typing.Union[typing.Annotated[int, Field(ge=1, le=16, strict=True)], Literal["auto"]]
#: The finest stage's field grid over the camera's: 1, 2, or ``"auto"`` (a model part, as :data:`SubSlices`).
FieldOversampling = typing.Union[typing.Annotated[int, Field(ge=1, le=2, strict=True)], Literal["auto", "before_spectral"]]
#: ``field_oversampling``'s value that tries the 2x field grid only where the spectral model would be kept without it.
BEFORE_SPECTRAL = "before_spectral"


def grid_to_choose(field_oversampling: int | str) -> bool:
    """Whether ``field_oversampling`` leaves the 2x field grid (part ``field_grid``) to the data: ``"auto"`` or
    ``"before_spectral"``."""
    return field_oversampling in ("auto", BEFORE_SPECTRAL)

#: The value of a setting chosen from the data.
AUTO = "auto"

COHERENCE_MODELS: tuple[str, ...] = typing.get_args(CoherenceModel)
COARSE_MODELS: tuple[str, ...] = typing.get_args(CoarseModel)
BACKWARD_MODES: tuple[str, ...] = typing.get_args(_BackwardModeValues)

_POSITIVE_DEPTH = typing.Annotated[float, Field(gt=0, strict=True)]


@schema_dataclass(root="stages[]", prefix="stages[].")
class StageConfig:
    """One coarse-to-fine stage: lateral ``factor`` (stage pixel = factor × acquisition pixel), ``iterations``
    and optionally its own ``batch_size`` (None: the configuration's). A coarse stage's images are
    ``factor²`` times smaller: on a GPU, where a small step costs its kernel launches rather than its
    arithmetic, a larger batch there uses more data for about the same time per iteration."""

    factor: int = setting(1, ge=1, description="stage pixel = factor × acquisition pixel", fix="use 4, 2, 1 for three stages")
    iterations: int = setting(100, ge=0, description="iterations of the stage", fix="e.g. 100")
    batch_size: Optional[typing.Annotated[int, Field(ge=1, strict=True)]] = setting(
        None, strict=False, description="images per iteration in this stage; null: the configuration's `batch_size`",
        fix="leave it out to use the configuration's batch_size")


def _default_stages() -> list[StageConfig]:
    return [StageConfig(4, 100), StageConfig(2, 100), StageConfig(1, 160)]


@schema_dataclass(root="config")
class SolverConfig:
    """Settings of a reconstruction. Learning rates are Adam step sizes in the parameters' own units."""

    # coarse-to-fine
    stages: list[StageConfig] = setting(
        default_factory=_default_stages, strict=False,
        description="coarse-to-fine stages; each factor must divide the previous one; a stage may carry its own `\"batch_size\"`",
        fix='e.g. [{"factor": 2, "iterations": 50}, {"factor": 1, "iterations": 100}]', tier="basic")
    coarse_model: CoarseModel = setting(
        "auto", strict=False, description="model of stages with factor > 1: `\"envelope\"` (cheap on CPU; on CUDA all sources and slices "
        "in one batch), `\"multislice\"` (exact, the cost of the fine stage when the camera samples the pupil near Nyquist), `\"auto\"`: "
        "envelope on CPU, multi-slice on CUDA, where it was the more accurate on the demo ([benchmarks.md](benchmarks.md))")
    batch_size: int = setting(16, ge=1, description="images per iteration", tier="basic")
    final_stage_min_passes: float = setting(
        24.0, ge=0, description="the finest stage runs at least this many passes over the images (iterations × batch / "
        "images; a pass visits every source once): acquisitions with many images get more iterations, since each source's "
        "position and gain are fitted only when its own image is in a batch; 0 keeps the stages' iterations "
        "(docs/decisions/finest-stage-length.md)")
    # RI grid
    delta_n_max: float = setting(0.1, gt=0, description="bound of Δn (absolute RI units)")
    activation: Activation = setting("paper", strict=False, description="`\"paper\"` (Δn ≥ 0) or `\"signed\"`")
    lr_ri: float = setting(0.05, gt=0, description="Adam step of the RI parameters (activation input units)")
    lr_ri_final_ratio: float = setting(
        1.0, gt=0, le=1, description="the RI step at the end of the finest stage over `lr_ri`: the step falls along that stage "
        "as ½(1 + cos(π·t))·(1 − r) + r (t from 0 to 1); 1 (the default) keeps it constant: a fall to 0.1 fitted the held-out "
        "images better but gave a larger Δn error on each of three seeds of letters_clean (docs/decisions/run-to-run-spread.md)", tier="experimental")
    # losses
    l1_l2_total: float = setting(1.0, ge=0, description="α + β", fix="0 switches the term off")
    l1_ramp_start: float = setting(0.0, ge=0, le=1, description="fraction of the run where α starts rising from 0 (≤ `l1_ramp_end`)",
                                   fix="the L1 weight rises over this fraction of the run")
    l1_ramp_end: float = setting(1.0, ge=0, le=1, description="fraction of the run where α reaches `l1_l2_total`",
                                 fix="the L1 weight rises over this fraction of the run")
    ssim_weight: float = setting(0.0, ge=0, description="γ, weight of 1 − SSIM", fix="0 switches the term off")
    tv_xy_weight: AutoWeight = setting(
        "auto", strict=False, description="τ_xy, weight of the lateral total variation; `\"auto\"`: chosen by the validation error "
        "among 1, 3, 10, 30, 100 (docs/solver.md, needs a validation split; 1 without one)", fix='give a number >= 0 (0 switches the term off) or "auto"', tier="basic")
    tv_z_weight: AutoWeight = setting(
        "auto", strict=False, description="τ_z, weight of the axial total variation; `\"auto\"`: chosen with τ_xy (τ_z = τ_xy / 2)",
        fix='give a number >= 0 (0 switches the term off) or "auto"', tier="basic")
    # self-calibration
    calibrate_sources: bool = setting(True, description="fit each source's lateral position", tier="basic")
    calibrate_gain: bool = setting(True, description="fit each image's gain")
    calibrate_source_depth: bool = setting(True, description="fit a common offset of the source depths")
    calibrate_pixel_size: bool = setting(False, description="fit a global scale of the pixel size")
    calibrate_slice_spacing: bool = setting(False, description="fit a global scale of the slice spacing")
    calibration_from_stage: int = setting(1, ge=0, description="first stage (0-based) with position/optics calibration (gains from the start)",
                                          fix="0 calibrates from the start")
    lr_sources_um: float = setting(0.02, gt=0, description="step of the source positions, µm per iteration: with `source_step` "
                                   "`\"whitened\"` or `\"per_visit\"` the mean step per iteration (a visit every N/B iterations steps "
                                   "`lr_sources_um × N/B`, at most λ/(4·NA); both × `multislice_source_step_scale` in multi-slice stages); with `\"dense\"` Adam's step")
    lr_log_gain: float = setting(0.01, gt=0, description="Adam step of the log-gains")
    lr_global: float = setting(1e-3, gt=0, description="Adam step of the pixel-size and slice-spacing scales (relative)")
    source_depth_um: Optional[_POSITIVE_DEPTH] = setting(None, strict=False, description="depth guess when the acquisition has no `sources_um`, µm")
    # partial coherence
    coherence: CoherenceModel = setting(
        "auto", strict=False, description="`\"none\"`, `\"mask\"`, `\"spectral\"` (an emission band of `bandwidth_um`), "
        "`\"mask+spectral\"`; `\"auto\"`: spectral where it lowers the validation error by more than noise, else none "
        "(docs/solver.md, \"Model parts\")")
    mask_threshold: float = setting(0.5, gt=0, lt=1, description="mask binarisation level, fraction of each image's maximum",
                                    fix="the paper binarises at about 0.5 of the maximum")
    bandwidth_um: float = setting(0.03, ge=0, description="emission FWHM for the spectral model, µm")
    n_wavelengths: int = setting(3, ge=1, description="wavelengths of the spectral model")
    # run
    seed: int = setting(0, description="batch order; a fixed seed gives the same result twice on CPU", tier="basic")
    snapshot_every: int = setting(10, ge=1, description="iterations between progress snapshots")
    checkpoint_every_s: float = setting(
        300.0, ge=0, description="with a checkpoint folder (`--checkpoint-dir`): seconds between the checkpoints written inside a "
        "stage, at its snapshots, counted in computation (not the time a consumer holds a snapshot; the latest kept; a stage's "
        "end always writes one); 0: at every snapshot")
    backward_mode: BackwardMode = setting(
        "auto", strict=False, description="how the multi-slice model forms gradients (`napari_fdt.model.slice_loop`): `\"stored\"` (one field per slice and "
        "image, fastest), `\"reversible\"` (re-propagates the field backwards: memory independent of the number of slices; grids without "
        "evanescent frequencies only), `\"checkpoint\"` (≈2√N fields), `\"autograd\"` (plain autograd, the reference); `\"auto\"`: "
        "stored when it fits in 80 % of the free memory, else the leanest valid mode", fix="auto picks the fastest that fits in memory")
    obliquity_correction: Switch = setting(
        "auto", strict=False, description="scale each source's phase screens by 1/cos θ of its ray (the thin screen's obliquity error, "
        "`docs/physics.md` §6; multi-slice stages, plain autograd): `true`, `false`, or `\"auto\"`: on where it lowers the validation "
        "error by more than noise (docs/solver.md, \"Model parts\")", fix="use \"auto\", true or false")
    # validation
    validation_fraction: float = setting(
        0.1, ge=0.0, le=0.25, description="share of the images held out of training, spread over the field (at least 3, at most a quarter; "
        "0: none). Their error, predicted through the volume with closed-form gains, is the validation error of every snapshot and of "
        "RI.json: how far to trust the volume without ground truth, and what `\"auto\"` weights and early stopping are chosen by. "
        "Held-out images still fit their own position and gain, never the volume",
        fix="0.1 holds out 10 %; 0 turns validation off", tier="basic")
    half_set_resolution: bool = setting(
        False, description="after the run, reconstruct each half of the images again with the run's choices and compare the "
        "two volumes (Fourier shell correlation at 1/7, and the optics' band limit): the lateral and axial resolution in "
        "RI.json. Two runs on half of the images (1.1-1.7 runs' time on the suite); an error both halves share is not seen, "
        "so the figure is a best case (docs/guide.md, \"What size of structure can I believe?\")",
        fix="true or false")
    error_bounds: bool = setting(
        False, description="after the run, a per-voxel error bound in RI units beside the volume (RI_bounds.tif; |Δn − "
        "Δn_true| ≤ bound on about 90 % of the voxels of simulated scenes like the calibration's): the result re-simulated "
        "with fresh noise and reconstructed with the run's choices, twice; their bias and spread, calibrated on simulated "
        "scenes (docs/guide.md, \"Can I believe this structure?\")",
        fix="true or false")
    tv_family: Switch = setting(
        "auto", description="reconstruct a family of volumes, one whole run per TV weight (τ_xy 1, 3 and 10, τ_z half of it), "
        "instead of choosing the weight by trials: each member's held-out error against the best member's (paired, with its "
        "standard error), and the pick (the largest weight within 5 % of the best held-out error that the images cannot tell "
        "from it). `fdt reconstruct` writes the pick to --out and the other members beside it. About two to three runs' time. "
        "`\"auto\"`: `fdt reconstruct` makes the family on a CUDA device (about 1.8-2.1x a run there) unless something it "
        "asks for excludes one (TV weights as numbers, --resume of one run's checkpoints, torchrun, half_set_resolution, "
        "error_bounds); one run on the CPU (docs/decisions/tv-family.md). With --checkpoint-dir each member writes its own "
        "checkpoints there (tv<weight>/), and --resume of that folder resumes the family. Under torchrun `\"true\"` runs "
        "each member distributed (`\"auto\"` one run). A `Reconstructor` is one run "
        "whatever this says (docs/solver.md, \"A family of volumes across TV weights\")",
        fix="auto, true or false", tier="basic", strict=False)
    early_stopping: EarlyStopping = setting(
        "best", strict=False, description="`\"best\"`: each stage ends on its iterate of lowest validation error (when the last is worse "
        "by more than `early_stopping_tolerance`); `\"stop\"`: also ends a stage once the error has stayed above its best for "
        "`early_stopping_patience` snapshots; `\"off\"`: the last iterate. Needs a validation split",
        fix="choose best, stop or off")
    early_stopping_patience: int = setting(3, ge=1, description="snapshots above the best validation error before `\"stop\"` ends a stage")
    early_stopping_tolerance: float = setting(
        0.02, ge=0.0, description="relative rise of the validation error over its best that counts as worse (below it: noise of the "
        "optimisation, the later iterate is kept)")
    # source-position steps (issue 12, item 4; docs/decisions/source-steps.md)
    source_step: SourceStep = setting(
        "whitened", strict=False, description="how each source's position steps: `\"whitened\"`: one step per visit (when its image is in "
        "the batch) of `lr_sources_um × N/B` (N images, B per batch), scaled by the inverse square root of the 3×3 mean outer "
        "product of its gradients (full-matrix Adam per source: it follows the valley where depth and lateral position move "
        "the image alike); `\"per_visit\"`: the same step with one scalar scale per source; `\"dense\"`: plain Adam on every "
        "row (it moves a row about `lr_sources_um·√(N/B)` per visit). No per-visit step is longer than λ/(4·NA) "
        "(× `multislice_source_step_scale` in multi-slice stages)",
        fix="choose whitened, per_visit or dense", tier="experimental")
    calibrate_sources_in_envelope_stages: bool = setting(
        True, description="fit the source positions and the depth offset in the coarse envelope stages too (from "
        "`calibration_from_stage`); false: they train from the first multi-slice stage on (the envelope model alone biases "
        "them, docs/solver.md; measured worse on cells and the 128² scene with the default schedule)", tier="experimental")
    calibrate_source_depth_in_envelope_stages: bool = setting(
        True, description="with the positions calibrated in envelope stages, fit their depths (each source's own and the common "
        "offset) there too; false: only x, y move there, the depths from the first multi-slice stage on (the envelope model "
        "pulls the common depth offset off, docs/solver.md)", tier="experimental")
    restart_source_moments: bool = setting(
        True, description="restart the optimiser moments of the source positions and of the depth offset at the start of "
        "every stage: the gradients of the previous stage's model and grid (an envelope stage's, biased and of another "
        "scale) no longer steer or scale the steps (docs/decisions/source-steps.md)", tier="experimental")
    multislice_source_step_scale: float = setting(
        2.0, gt=0, description="scale of the per-visit step of the source positions and of its cap (λ/(4·NA)) in multi-slice "
        "stages (`source_step` `\"whitened\"` or `\"per_visit\"`; envelope stages keep 1): seen from 50 µm below a volume "
        "15 µm thick, a source's shift moves the volume's shadow on the camera by a fraction of itself, so its image's loss "
        "stays smooth over more than a quarter of the resolution (docs/decisions/source-steps.md)", tier="experimental")
    source_step_schedule: SourceStepSchedule = setting(
        "constant", strict=False, description="per-visit step of the source positions along a multi-slice stage (`\"whitened\"`, "
        "`\"per_visit\"`): `\"constant\"`; `\"cosine\"`: each source's step falls as ½(1 + cos(π·v/V)) from its first to its "
        "V-th visit (V = iterations·B/N, the visits the stage gives it), long early steps and short late ones",
        fix="choose constant or cosine", tier="experimental")
    lr_depth_offset_um: float = setting(0.02, gt=0, description="Adam step of the common depth offset of the sources, µm per iteration")
    # camera and objective (docs/physics.md §3; issue 13)
    pixel_integration: PixelIntegration = setting(
        "auto", strict=False, description="record each pixel's mean intensity over its area instead of the value at its centre: "
        "`\"auto\"`: what `acquisition.json`'s `pixel_integration` says, else on when the intensity's band 2·NA/λ exceeds "
        "the camera's Nyquist 1/(2·pixel_size_um) (every camera integrates; the data cannot choose it: docs/solver.md, "
        "\"Model parts\"); `true`, `false` (JSON booleans or strings). Multi-slice stages",
        fix="use \"auto\", true or false")
    sub_slices: SubSlices = setting(
        "auto", strict=False, description="screens per slice in multi-slice stages: each slice crossed in this many symmetric steps, "
        "so that diffraction inside thick slices is modelled (docs/physics.md, \"Sub-slices\"; its error falls as 1/sub_slices²); "
        "costs as many times the slice loop. `\"auto\"`: a model part of the finest stage, tried with 2 where the slices are at "
        "least half the depth of field λ/(n_b(1 − cos θ)) and kept where the held-out images show it (the finest stage then "
        "runs again with it; docs/decisions/model-parts.md); one screen elsewhere",
        fix="\"auto\", 1 (one thin screen per slice), or 2-4 for slices thick against the depth of field")
    field_oversampling: FieldOversampling = setting(
        "before_spectral", strict=False, description="the finest stage's field on a grid this many times finer than the "
        "camera's (2: light the sample scatters beyond the camera grid's Nyquist is propagated, not aliased; docs/physics.md, "
        "\"A finer field grid\"); about 4× the finest stage's cost and memory. `\"auto\"`: a model part tried with 2 where the "
        "camera grid's Nyquist 1/(2·pixel_size_um) is below the medium's n_b/λ and the finest stage fits in memory with it, "
        "kept where the held-out images show it (the finest stage or every stage runs again with it), at a trial's and a branch's cost in "
        "every run. `\"before_spectral\"` (the default): the same part, tried only where the spectral model would be kept, "
        "and before it: that model's blur can absorb what a too-coarse field grid aliases (beads made on the 2x grid kept it "
        "in the grid's place; docs/decisions/parts-backward.md); elsewhere the run is the camera grid's to the bit",
        fix="1 (the camera grid), 2, \"auto\" or \"before_spectral\"")
    field_window: FieldWindow = setting(
        "auto", strict=False, description="window the multi-slice model's fields run on: `\"full\"` (each source's whole field, on a "
        "window that keeps its periodic copies off the image: 7-16x the image's area on the suite), `\"split\"` (the sources' "
        "field exact and non-periodic, only what the sample adds on the image and its light cone: 17-52 % of the pixels on the suite, "
        "as accurate; docs/decisions/split-field.md), `\"auto\"`: split on CPU where its window has at most 60 % of the full "
        "window's pixels, else full (on CUDA full: the split step measured 2.6-3.8x slower there, launch-bound); "
        "the 2x field grid with pixel means or an odd image size runs on the full window (the 2x grid otherwise splits "
        "too, and so do the per-source obliquity screens: docs/decisions/split-field.md)",
        fix="use \"auto\", \"full\" or \"split\"")
    pupil_edge: Optional[typing.Annotated[float, Field(ge=0.0, lt=0.5)]] = setting(
        None, strict=False, description="half-width of the pupil's raised-cosine edge relative to NA/λ (0: a hard pupil, held "
        "exactly); null: `acquisition.json`'s `pupil_edge`, else 0.03", fix="0 for a hard pupil, 0.03 the default soft edge")
    calibrate_pupil: Switch = setting(
        "auto", strict=False, description="fit the pupil's NA (a global scale) and edge width (multi-slice stages): `true`, `false`, or "
        "`\"auto\"`: where the fit lowers the validation error by more than noise (docs/solver.md, \"Model parts\")",
        fix="use \"auto\", true or false")
    calibrate_aberrations: Switch = setting(
        "auto", strict=False, description="fit a pupil phase of Zernike modes: defocus, astigmatism, coma, primary spherical (radians, Noll; "
        "multi-slice stages): `true`, `false`, or `\"auto\"`: where the fit lowers the validation error by more than noise "
        "(docs/solver.md, \"Model parts\")", fix="use \"auto\", true or false")
    parts_rerun: PartsRerun = setting(
        "stages", strict=False, description="when the \"auto\" choice of model parts keeps a part: `\"stages\"` runs every stage again from "
        "the first with the kept parts on (coarse stages multi-slice when `coarse_model` is `\"auto\"`, since the envelope "
        "model holds none of the parts) and chooses the other auto parts again in the finest stage; `\"finest\"` runs only "
        "the finest stage again (cheaper; the coarse volume keeps what it absorbed of the parts; docs/solver.md, \"Model parts\")",
        fix="use \"stages\" or \"finest\"", tier="experimental")
    parts_backward: bool = setting(
        True, description="once the final set of \"auto\" model parts is trained, test each kept part for removal on the held-out "
        "images (the admission's paired test); a part that no longer helps is dropped and the finest stage runs again without "
        "it, kept where the held-out images are not worse by more than noise (docs/solver.md, \"Model parts\")",
        fix="use true or false", tier="experimental")
    parts_branch: bool = setting(
        True, description="where the trial through the volume rejects sub-slices or the 2x field grid (a volume trained without "
        "them has adapted to the simpler model), try them again by a short branch of training: 5 % of the finest stage's "
        "iterations from its end with the part and without it, the held-out images paired at the two ends; a part kept "
        "so makes every stage run again with it, the other parts tried in that pass (docs/decisions/parts-backward.md)",
        fix="use true or false", tier="experimental")
    parts_pilot: bool = setting(
        True, description="also choose the \"auto\" pupil parts (`calibrate_pupil`, `calibrate_aberrations`) before the finest stage: "
        "the pupil before the stages, from a pilot at Δn = 0 (the sources' positions and gains fitted through the finest stage's "
        "model, then the paired test; a part kept there is on from the first stage, so no stage runs twice for it), and the "
        "aberrations at the last coarse stage's end, through its volume (kept there, every stage runs again before the "
        "finest stage has run once, and that pass tests the pupil at the same stage's end: kept then, on from the finest "
        "stage's start); a part not kept is tried again at the finest stage's end "
        "(docs/solver.md, \"Model parts\")")
    parts_test_images: PartsTestImages = setting(
        "held_out+training", strict=False, description="images the paired test of the \"auto\" model parts runs on: `\"held_out\"` "
        "(the validation split) or `\"held_out+training\"` (also the training images a part's parameters are not fitted to: "
        "more images, more power; biased against a part, since the volume was trained without it; the default: with the held-out images alone "
        "beads_real missed its aberration and beads_clean kept a spectral model it does not have; docs/solver.md, \"Model parts\")",
        fix="use \"held_out\" or \"held_out+training\"", tier="experimental")
    lr_pupil: float = setting(1e-3, gt=0, description="Adam step of the NA scale (relative) and the pupil edge width")
    lr_aberrations: float = setting(0.02, gt=0, description="Adam step of the Zernike coefficients, radians")

    @model_validator(mode="after")
    def _cross_field(self) -> "SolverConfig":
        """Rules between fields: at least one stage, factors dividing each other, the L1 ramp in order."""
        if not self.stages:
            raise FDTInputError("stages", "is empty", "give at least one stage, e.g. [{\"factor\": 1, \"iterations\": 100}]")
        for a, b in zip(self.stages, self.stages[1:]):
            if a.factor % b.factor:
                raise FDTInputError("stages", f"factor {a.factor} is followed by {b.factor}, which does not divide it",
                                    "use decreasing factors that divide each other, e.g. 4, 2, 1")
        if not (self.l1_ramp_start <= self.l1_ramp_end):
            raise FDTInputError("l1_ramp_start", f"must satisfy 0 <= l1_ramp_start <= l1_ramp_end <= 1, got {self.l1_ramp_start} > {self.l1_ramp_end}",
                                "the L1 weight rises over this fraction of the run")
        return self

    def stage_batch(self, stage_index: int) -> int:
        """Batch size of a stage: its own ``batch_size``, else the configuration's."""
        b = self.stages[stage_index].batch_size
        return self.batch_size if b is None else b

    @property
    def total_iterations(self) -> int:
        return sum(s.iterations for s in self.stages)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "SolverConfig":
        if not isinstance(data, dict):
            raise FDTInputError("config", f"must be a JSON object, got {type(data).__name__}", "see docs/settings.md")
        return cls(**data)

    def save(self, path: str | Path) -> None:
        from napari_fdt.data.io import write_json_atomic

        write_json_atomic(path, self.to_dict(), overwrite=True)


def resolve_stage_lengths(config: SolverConfig, n_images: int) -> SolverConfig:
    """The configuration with the finest stage lengthened to ``final_stage_min_passes`` passes over ``n_images``
    images: ``iterations ≥ ceil(passes · N / B)`` (B its batch, at most N). Unchanged (the same object) when the
    stage is already that long or the setting is 0; applying it twice changes nothing more.

    Why: a source's position (and gain) gets a gradient only when its own image is in the batch, B/N of the
    iterations, so a fixed iteration count calibrates the sources of a large acquisition less: 160 iterations are
    40 passes on the bundled sample (64 images) but 13 on 196 images, where the positions stalled at 0.26-0.30 µm.
    """
    if config.final_stage_min_passes <= 0 or not config.stages or n_images <= 0:
        return config
    finest = len(config.stages) - 1  # each factor divides the previous one: the last stage is the finest
    stage = config.stages[finest]
    if stage.iterations <= 0:
        return config
    batch = min(config.stage_batch(finest), n_images)
    need = math.ceil(config.final_stage_min_passes * n_images / batch - 1e-9)
    if stage.iterations >= need:
        return config
    stages = list(config.stages)
    stages[finest] = dataclasses.replace(stage, iterations=int(need))
    return dataclasses.replace(config, stages=stages)


def resolve_coarse_model(coarse_model: str, device_type: str) -> str:
    """``"auto"`` → ``"multislice"`` on CUDA, ``"envelope"`` elsewhere; other values pass through."""
    if coarse_model != "auto":
        return coarse_model
    return "multislice" if device_type == "cuda" else "envelope"


def load_config(path: str | Path) -> SolverConfig:
    """Read a configuration file (JSON; also TOML when the name ends in .toml)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise FDTInputError("config", f"cannot read {p}: {exc.strerror or exc}", "check the path") from None
    try:
        if p.suffix.lower() == ".toml":
            try:
                import tomllib
            except ImportError:  # Python 3.10
                raise FDTInputError("config", "TOML needs Python >= 3.11", "write the configuration as JSON") from None
            data = tomllib.loads(text)
        else:
            data = json.loads(text)
    except (ValueError, json.JSONDecodeError) as exc:
        raise FDTInputError("config", f"{p} does not parse: {exc}", "write valid JSON (or TOML for .toml)") from None
    return SolverConfig.from_dict(data)


def settings_markdown() -> str:
    """The settings table of ``docs/settings.md``, generated from :class:`SolverConfig` and :class:`StageConfig`."""
    return markdown_table(SolverConfig) + "\n" + "Each entry of `stages`:\n\n" + markdown_table(StageConfig)

