"""The reconstruction: one solver loop, exposed as a generator of snapshots.

``Reconstructor(acquisition, config).run()`` yields a :class:`Snapshot` every ``snapshot_every``
iterations and at the end of every stage (``stage_complete=True``). Stopping the iteration (or calling
``close()`` on the generator) cancels between iterations; :attr:`Reconstructor.last_complete` then holds
the last complete stage. The command line, the napari widgets and the benchmarks all drive this loop.

What is optimised (``docs/solver.md``): the explicit RI grid (:class:`~napari_fdt.recon.volume.RIVolume`), a
log-gain per image, and (from ``calibration_from_stage``) the lateral position of every source, a common
offset of the source plane's depth, and optionally the pixel size and slice spacing as global scales.
The RI grid has its own Adam optimiser, rebuilt at each stage (its moments belong to voxels that the
resampling replaces); the calibration parameters (:class:`~napari_fdt.recon.calibration.Calibration`) keep
one Adam optimiser for the whole run. Checkpoints are :mod:`napari_fdt.recon.checkpoint`'s, the checks
before a run :mod:`napari_fdt.recon.preflight`'s.

Given a :class:`~napari_fdt.recon.distributed.Group` (``group=``), the run is one rank of a data-parallel
reconstruction (``docs/distributed.md``): each rank computes the images it owns of every batch, the
gradients of the shared parameters are summed over ranks, and the result equals the single-process one.
"""

from __future__ import annotations

import copy
import dataclasses
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Generator, Iterator, Sequence

import numpy as np
import torch

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.device import resolve_device
from napari_fdt.errors import FDTInputError, FDTWarning
from napari_fdt.model.coherence import coherence_masks, emission_spectrum, spectral_images
from napari_fdt.model.gain import least_squares_gain
from napari_fdt.model.render import iter_batches
from napari_fdt.recon.batches import BatchOrder
from napari_fdt.recon.calibration import Calibration
from napari_fdt.recon.checkpoint import checkpoint_path, checkpoint_state, read_checkpoint, restore_checkpoint, write_checkpoint
from napari_fdt.recon.config import SolverConfig, resolve_coarse_model, resolve_stage_lengths
from napari_fdt.recon.losses import BatchShare, LossWeights, as_floats, total_loss
from napari_fdt.recon.model_parts import (
    BINARY_PARTS,
    FIT_IMAGES,
    FIT_ITERATIONS,
    FIT_RATES,
    FITTED_PARTS,
    PARTS,
    PartsChoice,
    decide,
    parts_stage,
    requested_parts,
)
from napari_fdt.recon.phases import RERUN, RUN, TV_CHOICE, phase_counts, probe_iterations, work_left
from napari_fdt.recon.phases import phase_label as _phase_label
from napari_fdt.recon.preflight import check_backward_mode, check_memory, warn_about_images, warn_about_sampling
from napari_fdt.recon.regularisation import TV_PATH, TVChoice, candidate_weights, pick, selection_stages, tv_is_auto
from napari_fdt.recon.schedule import final_step_scale
from napari_fdt.recon.stages import Stage, build_stage, camera_model_options, stated_pixel_integration
from napari_fdt.recon.validation import BestIterate, holdout_indices, per_image_errors, relative_image_error
from napari_fdt.recon.volume import RIVolume, upsample_to

if TYPE_CHECKING:
    from napari_fdt.recon.distributed import Group

__all__ = ["Snapshot", "StageRecord", "Reconstructor", "reconstruct"]


@dataclass
class Snapshot:
    """The state of a running reconstruction.

    ``delta_n`` is Δn on the stage grid (n_slices, h, w) (``delta_n_full()`` upsamples it to the
    acquisition grid); ``sources_um`` (N, 3) the calibrated positions (acquisition coordinates);
    ``gains`` (N,); ``calibration`` the global parameters; ``losses`` the loss terms of the last
    iteration (unweighted); ``validation_error`` / ``train_error`` the relative image errors of the held-out
    images and of the last batch (:mod:`napari_fdt.recon.validation`); times in seconds.
    """

    stage: int
    n_stages: int
    factor: int
    iteration: int
    stage_iterations: int
    global_iteration: int
    total_iterations: int
    delta_n: np.ndarray
    sources_um: np.ndarray
    gains: np.ndarray
    calibration: dict[str, float]
    losses: dict[str, float]
    elapsed_s: float
    eta_s: float
    stage_complete: bool
    full_shape: tuple[int, int]
    #: relative RMS error of the held-out images predicted through the volume (closed-form gains; None: no split)
    validation_error: float | None = None
    #: the same error on the last training batch (its trained gains; this rank's part in a distributed run)
    train_error: float | None = None
    #: the model parts the data needed when the stages run again with them (``parts_rerun``): the iteration count
    #: then starts again from the first stage; empty during the first pass
    rerun_with: tuple[str, ...] = ()
    #: "tv_choice" for snapshots of the pilot that chooses the TV weight, "run" for the pass, "rerun" for the stages run
    #: again with kept model parts (:mod:`napari_fdt.recon.phases`: the counts of each)
    phase: str = RUN
    #: iterations done in this phase, and in it in all (the pilot: its stages', then the trials'); in "run" and "rerun"
    #: equal to ``global_iteration`` and ``total_iterations``
    phase_iteration: int = 0
    phase_iterations: int = 0
    #: (τ_xy, τ_z) the pilot has just tried (a trial's snapshot: ``validation_error`` is the trial's); None otherwise
    tv_weights: tuple[float, float] | None = None

    @property
    def phase_label(self) -> str:
        """The phase in plain English: "choosing the smoothing (TV) weight", "reconstructing", "reconstructing again with …"."""
        return _phase_label(self.phase, self.rerun_with, self.tv_weights)

    @property
    def phase_progress(self) -> float:
        """The share of this phase done (:attr:`progress` when the phase's count is not given)."""
        return self.phase_iteration / self.phase_iterations if self.phase_iterations > 0 else self.progress

    def delta_n_full(self) -> np.ndarray:
        """Δn on the acquisition grid (n_slices, H, W), float32."""
        t = torch.from_numpy(self.delta_n)
        return upsample_to(t, self.factor, self.full_shape).numpy()

    @property
    def progress(self) -> float:
        return self.global_iteration / max(1, self.total_iterations)


@dataclass
class StageRecord:
    """What one stage did, for the report."""

    stage: int
    factor: int
    field_factor: int
    grid: tuple[int, int, int]
    window: tuple[int, int]
    na: float
    iterations: int
    seconds: float = 0.0
    model: str = "multislice"
    #: validation error the stage ended on, its iteration (earlier than ``iterations`` when the best iterate was
    #: kept), and the iteration early stopping ended the stage at (None: it ran to the end)
    validation_error: float | None = None
    best_iteration: int | None = None
    stopped_at: int | None = None

    @property
    def seconds_per_iteration(self) -> float:
        ran = self.stopped_at or self.iterations  # early stopping ends a stage before its iterations
        return self.seconds / ran if ran else 0.0

    def to_dict(self) -> dict[str, Any]:
        return {"stage": self.stage, "factor": self.factor, "field_factor": self.field_factor, "grid": list(self.grid), "window": list(self.window),
                "na": self.na, "model": self.model, "iterations": self.iterations, "seconds": self.seconds,
                "seconds_per_iteration": self.seconds_per_iteration, "validation_error": self.validation_error,
                "best_iteration": self.best_iteration, "stopped_at": self.stopped_at}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "StageRecord":
        """The inverse of :meth:`to_dict`."""
        return cls(d["stage"], d["factor"], d["field_factor"], tuple(d["grid"]), tuple(d["window"]), d["na"], d["iterations"],
                   d["seconds"], d["model"], d.get("validation_error"), d.get("best_iteration"), d.get("stopped_at"))


class Reconstructor:
    """A reconstruction of one acquisition with one configuration.

    Parameters
    ----------
    acquisition: the data.
    config: solver settings.
    device: ``"auto"``, ``"cpu"`` or ``"cuda"``.
    initial_sources_um: (N, 3) start positions; default the acquisition's ``sources_um``, else the
        2D-Gaussian fit of :mod:`napari_fdt.recon.source_fit` (with ``config.source_depth_um`` if given).
    group: this process's rank in a data-parallel run (:func:`napari_fdt.recon.distributed.setup`), None for
        one process. Every rank must then iterate :meth:`run` in step (it holds collectives); only rank 0
        writes checkpoints.

    Results: :meth:`delta_n_full` / :meth:`ri_full` (the volume), :meth:`sources_um` and :meth:`gains` (the
    calibration), :meth:`predict` (images of the current state, in the acquisition's units).
    """

    def __init__(
        self,
        acquisition: Acquisition,
        config: SolverConfig | None = None,
        *,
        device: str | torch.device = "auto",
        initial_sources_um: np.ndarray | None = None,
        group: Group | None = None,
    ) -> None:
        self.acquisition = acquisition
        self.group = group
        #: the configuration as given (what RI.json and checkpoints store: resolving it again gives the same run)
        self.requested_config = config or SolverConfig()
        #: the configuration as run: the finest stage lengthened to ``final_stage_min_passes`` passes over the images
        #: (:func:`napari_fdt.recon.config.resolve_stage_lengths`)
        self.config = resolve_stage_lengths(self.requested_config, acquisition.n_images)
        self.device = resolve_device(device)
        self.dtype = torch.float32
        cfg = self.config
        #: the coarse stages' model after resolving "auto" for this device
        self.coarse_model = resolve_coarse_model(cfg.coarse_model, self.device.type)
        n_img = acquisition.n_images
        if initial_sources_um is None:
            if acquisition.sources_um is not None:
                initial_sources_um = acquisition.sources_um
            else:
                from napari_fdt.recon.source_fit import initial_sources

                initial_sources_um, self.source_fit_report = initial_sources(
                    acquisition, depth_um=cfg.source_depth_um, device=self.device
                )
        src = np.asarray(initial_sources_um, dtype=np.float64)
        if src.shape != (n_img, 3):
            raise FDTInputError("sources_um", f"need one [x, y, depth] per image ({n_img}), got shape {src.shape}",
                                "give one source per image")
        self.initial_sources_um = src.copy()
        imgs = acquisition.images_float32().astype(np.float32)
        mean = float(imgs.mean(dtype=np.float64))
        if not mean > 0:
            raise FDTInputError("images", "are all zero (or their mean is not positive)", "check the acquisition")
        #: the acquisition's mean intensity; the solver works on images divided by it
        self.image_scale = mean
        warn_about_images(acquisition)
        warn_about_sampling(acquisition, src)  # before any run
        #: (N, H, W) float32 images / image_scale, on the CPU (each stage averages them to its grid)
        self.images = torch.from_numpy(imgs / mean)
        self.full_shape = acquisition.image_shape
        self.calibration = self._new_calibration()
        self.volume: RIVolume | None = None
        self.volume_factor: int | None = None
        #: (V,) indices of the held-out images, spread over the field (empty: no validation). They are drawn in
        #: batches like the others, but their loss reaches only their own position and gain: never the volume
        #: nor the shared calibration (a fit of their positions that does not touch the volume).
        self.validation_indices = holdout_indices(src, cfg.validation_fraction)
        self._held_out = torch.zeros(n_img, dtype=torch.bool, device=self.device)
        self._held_out[torch.as_tensor(self.validation_indices, dtype=torch.long, device=self.device)] = True
        self.batches = BatchOrder(n_img, cfg.seed, self.device)
        self.completed_stages = 0
        self.stages: list[StageRecord] = []
        self.history: list[dict[str, Any]] = []
        self.elapsed_s = 0.0
        self.last_complete: Snapshot | None = None
        self.final_losses: dict[str, float] = {}
        #: the optional model parts (:mod:`napari_fdt.recon.model_parts`) as now switched; "auto" ones are off until chosen
        self.parts: dict[str, bool] = {}
        #: what the choice of the "auto" parts tried and chose (None until made)
        self.parts_choice: PartsChoice | None = None
        self.wavelengths, self.weights = None, None
        #: auto parts the finest stage chooses again after every stage ran again with the kept ones (``parts_rerun``)
        self._choose_again: list[str] = []
        #: whether :meth:`run` must run the stages again from the first (set by the first choice that keeps a part)
        self._restart_pending = False
        #: whether the pilot is running (its snapshots are phase "tv_choice")
        self._piloting = False
        self._init_parts()
        self.loss_weights = LossWeights.from_config(cfg)
        #: the TV weights chosen from the data ("auto"; :mod:`napari_fdt.recon.regularisation`), None until chosen
        #: or when the weights are fixed numbers
        self.tv_choice: TVChoice | None = None
        if tv_is_auto(cfg) and not len(self.validation_indices):
            warnings.warn("tv_xy_weight: \"auto\" chooses the TV weights by the validation error, and this run holds no "
                          "images out (validation_fraction 0, or too few images): TV is off. Give validation_fraction > 0 "
                          "or fixed weights", FDTWarning, stacklevel=2)
            self.tv_choice = TVChoice(*candidate_weights(cfg, 0.0), stage=0, probe_iterations=0, reason="no validation split")
        check_backward_mode(acquisition, cfg, src, self.device)
        check_memory(acquisition, cfg, src, self.device, len(self.wavelengths) if self.wavelengths else 1)

    # -- the algorithm --------------------------------------------------------------------------
    def run(self, should_stop: Callable[[], bool] | None = None, checkpoint_dir: str | Path | None = None) -> Iterator[Snapshot]:
        """Run the remaining stages, yielding snapshots. ``should_stop()`` is polled between iterations.

        Per stage: build the stage's model and images for the current sources, carry the volume to its
        grid, make the loss mask, start the gains (once), switch the calibration on or off; then iterate
        (batch, predict, loss, step; a snapshot every ``snapshot_every``), and end with a snapshot and a
        checkpoint (``checkpoint_dir/stage_<i>.pt``).

        With ``"auto"`` TV weights, a pilot first runs the stages up to the selection stage and tries the weights there
        (:meth:`_pilot`; its snapshots are :attr:`Snapshot.phase` "tv_choice"); the run then starts from the beginning
        with the chosen weights (phase "run"; "rerun" when the stages run again with model parts).
        """
        if self.tv_choice is None and tv_is_auto(self.config) and self.completed_stages == 0:
            ok = yield from self._pilot(should_stop)
            if not ok:
                return
        yield from self._run_stages(should_stop, checkpoint_dir)
        if self._restart_pending:  # the choice kept a part: every stage again with it (parts_rerun "stages")
            self._restart_pending = False
            yield from self._run_stages(should_stop, checkpoint_dir)

    def _pilot(self, should_stop: Callable[[], bool] | None) -> Generator[Snapshot, None, bool]:
        """Choose the "auto" TV weights: run the stages before the selection stage as the run would (TV off), try the
        weights at the selection stage (:meth:`_choose_tv`), then return to the initial state with the weights set, so
        that the run equals one given them as numbers from its first stage on. Yields the snapshots meanwhile (phase
        "tv_choice"); returns False when cancelled meanwhile (closed or failed: back to the initial state too)."""
        t0 = time.perf_counter()
        self._piloting, finished = True, False
        try:
            for snap in self._run_stages(should_stop, None):  # ends at the selection stage, once the weights are tried
                paused = time.perf_counter()
                yield snap
                t0 += time.perf_counter() - paused  # the consumer's time is not the pilot's
            finished = True
        finally:
            self._piloting = False
            if not finished:
                self._restart()
        choice = self.tv_choice
        self._restart()
        if choice is None:  # cancelled
            return False
        choice.seconds = time.perf_counter() - t0
        self.tv_choice = choice
        self.loss_weights = dataclasses.replace(self.loss_weights, tv_xy=choice.tv_xy_weight, tv_z=choice.tv_z_weight)
        self.elapsed_s = choice.seconds  # the pilot's time is the run's
        return True

    def _restart(self) -> None:
        """Back to the state before any stage ran (volume, calibration and its optimiser, batch order, records)."""
        cfg = self.config
        self.calibration = self._new_calibration()
        self.batches = BatchOrder(self.acquisition.n_images, cfg.seed, self.device)
        self.volume, self.volume_factor = None, None
        self.completed_stages, self.stages, self.history = 0, [], []
        self.last_complete, self.final_losses = None, {}
        self.__dict__.pop("_last_complete_state", None)

    def _new_calibration(self) -> Calibration:
        """The calibration parameters at their start (the initial sources, the acquisition's optics)."""
        cal = Calibration(self.initial_sources_um, self.config, self.acquisition.optics, device=self.device, dtype=self.dtype,
                          pupil_edge=camera_model_options(self.config, self.acquisition)["pupil_edge"])
        if getattr(self, "parts", None):
            cal.fit_pupil, cal.fit_aberrations = self.parts["pupil"], self.parts["aberrations"]
        self._set_stage_roles(cal)
        return cal

    def _set_stage_roles(self, cal: Calibration) -> None:
        """Tell ``cal`` which stages run the envelope model and in which its positions or depths stay fixed (they
        follow :attr:`coarse_model`)."""
        cal.position_frozen_stages = position_frozen_stages(self.config, self.coarse_model)
        cal.depth_frozen_stages = depth_frozen_stages(self.config, self.coarse_model)
        cal.envelope_stages = envelope_stages(self.config, self.coarse_model)

    # -- optional model parts ---------------------------------------------------------------------
    def _init_parts(self) -> None:
        """Each part's switch before any choice: as set or stated, "auto" ones off; with nothing to choose (or no
        validation split to choose by) :attr:`parts_choice` is made at once."""
        cfg = self.config
        requested = requested_parts(cfg)
        chosen_by = {p: "setting" for p in PARTS}
        stated = stated_pixel_integration(cfg, self.acquisition)
        if cfg.pixel_integration == "auto" and stated is not None:
            chosen_by["pixel_integration"] = "acquisition"
        requested["pixel_integration"] = stated
        extra = getattr(self.acquisition, "extra", None) or {}
        if requested["pupil"] is None and "pupil_edge" in extra and cfg.pupil_edge is None:
            # a pupil the acquisition states (as fdt simulate writes it) is taken as stated, like its pixel integration
            requested["pupil"] = False
            chosen_by["pupil"] = "acquisition"
        #: the parts chosen from the data
        self._auto_parts = [p for p in PARTS if requested[p] is None]
        parts = {p: bool(requested[p]) for p in PARTS}
        if not self._auto_parts:
            self.apply_parts_choice(PartsChoice(parts, chosen_by))
        elif not len(self.validation_indices):
            for p in self._auto_parts:
                chosen_by[p] = "no validation split"
                if p == "pixel_integration":  # the physical rule stands in for the data (camera_model_options applies it)
                    parts[p] = camera_model_options(cfg, self.acquisition)["pixel_integration"]
                    chosen_by[p] = "no validation split: physical rule"
            self.apply_parts_choice(PartsChoice(parts, chosen_by))
        else:
            self._set_parts(parts)
        self._parts_chosen_by = chosen_by

    def _set_parts(self, parts: dict[str, bool]) -> None:
        """Switch the parts: the spectral model's wavelengths and the calibration's pupil and aberration fits (the stage
        models take :attr:`parts` when built)."""
        self.parts = dict(parts)
        o, cfg = self.acquisition.optics, self.config
        if parts["spectral"]:
            lams, ws = emission_spectrum(o.wavelength_um, cfg.bandwidth_um, cfg.n_wavelengths)
            self.wavelengths, self.weights = list(map(float, lams)), list(map(float, ws))
        else:
            self.wavelengths, self.weights = None, None
        self.calibration.fit_pupil = parts["pupil"]
        self.calibration.fit_aberrations = parts["aberrations"]

    def apply_parts_choice(self, choice: PartsChoice) -> None:
        """Take a choice of parts (made here, or read from a checkpoint): switches, and the fitted pupil values when the
        calibration has not moved them yet. A choice whose stages run again (``rerun`` ``"stages"``) also sets the coarse
        model they run with and the parts still to choose in the finest stage."""
        self.parts_choice = choice
        self._set_parts(choice.parts)
        if choice.rerun == "stages":
            self._use_rerun_coarse_model()
            self._choose_again = list(choice.pending)
            if choice.pending:
                self._auto_parts = list(choice.pending)
            self._parts_chosen_by = dict(choice.chosen_by)

    def _use_rerun_coarse_model(self) -> None:
        """The coarse stages of a run that holds the kept parts: multi-slice when ``coarse_model`` is ``"auto"`` (the
        envelope model holds none of the parts; a coarse model given by name is kept)."""
        if self.config.coarse_model == "auto":
            self.coarse_model = "multislice"
            self._set_stage_roles(self.calibration)

    def _restart_with_parts(self) -> None:
        """After a first choice that kept parts (``parts_rerun`` ``"stages"``): back to the state before any stage, with
        the kept parts on from the first stage (their parameters start from the fitted values and train from
        ``calibration_from_stage`` on) and the coarse stages multi-slice; the finest stage chooses the other auto parts
        again (now on top of the kept ones, through a volume trained with them)."""
        choice = self.parts_choice
        kept = [p for p in self._auto_parts if self.parts[p]]
        for t in choice.trials:
            t.setdefault("pass", 1)
        choice.rerun = "stages"
        choice.pending = [p for p in self._auto_parts if p not in kept]
        self.apply_parts_choice(choice)
        fitted = {name: getattr(self.calibration, name).detach().clone() for name in ("na_scale", "pupil_edge", "zernike")}
        self._restart()
        self.calibration.restore_values(fitted)  # the kept parts start from their fitted values
        self._restart_pending = True

    def _choose_parts(self, stage: Stage, mask: torch.Tensor | None, should_stop: Callable[[], bool] | None) -> Stage | None:
        """Choose the "auto" parts at the start of ``stage`` (:mod:`napari_fdt.recon.model_parts`) and return the stage
        as rebuilt for them; None when stopped meanwhile (the parts are then back to off)."""
        t0 = time.perf_counter()
        cal = self.calibration
        provisional = dict(self.parts)
        start_values = cal.copy_values()
        ref_err, ref_each = self._choice_errors(stage, mask)
        reference = (ref_err, list(ref_each))
        trials: list[dict[str, Any]] = []

        def cancel() -> None:
            cal.restore_values(start_values)
            self._set_parts(provisional)

        for part in [p for p in BINARY_PARTS if p in self._auto_parts]:
            if self._stop_requested(should_stop):
                cancel()
                return None
            t1 = time.perf_counter()
            self._set_parts({**self.parts, part: True})
            variant = stage if part == "spectral" else self._build_stage(stage.index)
            vmask = self._loss_mask(variant)
            err, each = self._choice_errors(variant, vmask)
            verdict = decide(ref_each, each)
            trials.append({"part": part, "validation_error": err, "image_errors": each, **verdict,
                           "seconds": time.perf_counter() - t1})
            if verdict["on"]:
                stage, mask, ref_each = variant, vmask, each
            else:
                self._set_parts({**self.parts, part: False})
        fitted_auto = [p for p in FITTED_PARTS if p in self._auto_parts]
        if fitted_auto:
            t1 = time.perf_counter()
            cache = self._exit_cache(stage)
            cache_s = time.perf_counter() - t1
            kept: list[str] = []
            for part in fitted_auto:
                t1 = time.perf_counter()
                before = cal.copy_values()
                if not self._fit_pupil_parts(stage, cache, [part], should_stop):
                    cancel()
                    return None
                self._set_parts({**self.parts, part: True})
                err, each = self._choice_errors(stage, mask)
                verdict = decide(ref_each, each)
                trials.append({"part": part, "validation_error": err, "image_errors": each, **verdict,
                               "fitted": self._pupil_values([part]), "seconds": time.perf_counter() - t1 + cache_s})
                cache_s = 0.0
                if verdict["on"]:
                    kept.append(part)
                    ref_each = each
                else:
                    self._set_parts({**self.parts, part: False})
                    cal.restore_values(before)
            if len(kept) > 1:  # refit together from the separate fits; kept if the held-out images agree
                t1 = time.perf_counter()
                before = cal.copy_values()
                if not self._fit_pupil_parts(stage, cache, kept, should_stop):
                    cancel()
                    return None
                err, each = self._choice_errors(stage, mask)
                joint = float(np.mean(each)) <= float(np.mean(ref_each))
                trials.append({"part": "+".join(kept), "validation_error": err, "image_errors": each, "on": joint,
                               "fitted": self._pupil_values(kept), "seconds": time.perf_counter() - t1})
                if joint:
                    ref_each = each
                else:
                    cal.restore_values(before)
        chosen_by = {p: ("validation" if p in self._auto_parts else self._parts_chosen_by[p]) for p in PARTS}
        choice = PartsChoice(dict(self.parts), chosen_by, stage=stage.index, reference_error=reference[0],
                             reference_image_errors=reference[1], trials=trials,
                             fitted=self._pupil_values([p for p in FITTED_PARTS if self.parts[p]]),
                             seconds=time.perf_counter() - t0)
        first = self.parts_choice
        if first is not None and first.rerun == "stages":  # the second pass's choice: both passes' trials, the first's reference
            choice.trials = first.trials + [{**t, "pass": 2} for t in trials]
            choice.reference_error, choice.reference_image_errors = first.reference_error, first.reference_image_errors
            choice.seconds += first.seconds
            choice.rerun = "stages"
            self._choose_again = []
        self.apply_parts_choice(choice)
        return stage

    def _choice_errors(self, stage: Stage, mask: torch.Tensor | None) -> tuple[float, list[float]]:
        """(validation error, per-image errors the parts' paired test compares): the held-out images', and with
        ``parts_test_images`` ``"held_out+training"`` also those of the training images the parts' parameters are not
        fitted to (more images, a stronger test; biased against a part, since the volume and their positions were
        trained without it)."""
        err, each = self._validation(stage, mask, per_image=True)
        if self.config.parts_test_images != "held_out+training":
            return err, each
        train = np.setdiff1d(np.setdiff1d(np.arange(self.acquisition.n_images), self.validation_indices),
                             self._fit_images().cpu().numpy())
        with torch.no_grad():
            dn = self.volume.delta_n()
            preds = [self._predict_normalised(stage, dn, torch.as_tensor(train[sl], device=self.device))
                     for sl in iter_batches(len(train), self.config.batch_size)]
        idx = torch.as_tensor(train, device=self.device)
        more = per_image_errors(torch.cat(preds), stage.images[idx], None if mask is None else mask[idx], fit_gain=True)
        return err, list(each) + list(more)

    def _pupil_values(self, parts: list[str]) -> dict[str, Any]:
        """The calibration's current pupil values of ``parts``: NA and edge, Zernike coefficients by mode (rad)."""
        from napari_fdt.physics.aberrations import ZERNIKE_MODES

        cal, out = self.calibration, {}
        if "pupil" in parts:
            out["na"] = self.acquisition.optics.na * float(cal.na_scale.detach())
            out["pupil_edge"] = abs(float(cal.pupil_edge.detach()))
        if "aberrations" in parts:
            out["zernike_rad"] = dict(zip(ZERNIKE_MODES, (float(v) for v in cal.zernike.detach().cpu())))
        return out

    def _fit_images(self) -> torch.Tensor:
        """Up to :data:`FIT_IMAGES` training images, evenly spread over them (the subset the pupil parts are fitted to)."""
        train = np.setdiff1d(np.arange(self.acquisition.n_images), self.validation_indices)
        pick_ = np.unique(np.round(np.linspace(0, len(train) - 1, min(FIT_IMAGES, len(train)))).astype(int))
        return torch.as_tensor(train[pick_], device=self.device)

    def _exit_cache(self, stage: Stage) -> list[tuple[torch.Tensor, list[tuple[float | None, float, torch.Tensor, torch.Tensor]]]]:
        """For chunks of the fit images: (indices, [(wavelength, weight, exit spectra, source spectra)]) through the current
        volume and sources (:meth:`MultiSliceModel.exit_spectra`), computed once for every pupil tried."""
        cal, model = self.calibration, stage.model
        base = {k: v for k, v in cal.optics_overrides(stage.optics, False, shared_frozen=True).items()
                if k not in ("na", "pupil_edge", "zernike")}
        lams = list(zip(self.wavelengths, self.weights)) if self.wavelengths else [(None, 1.0)]
        out = []
        with torch.no_grad():
            dn = stage.to_field_grid(self.volume.delta_n())
            idx_all = self._fit_images()
            for sl in iter_batches(len(idx_all), self.config.batch_size):
                idx = idx_all[sl]
                src = stage.stage_sources(cal.calibrated_sources()[idx])
                per = []
                for lam, w in lams:
                    k = model.kernels(**base, wavelength_um=lam) if (base or lam is not None) else None
                    per.append((lam, w, *model.exit_spectra(dn, src, k)))
                out.append((idx, per))
        self._exit_cache_base = base
        return out

    def _fit_pupil_parts(self, stage: Stage, cache, parts: list[str], should_stop: Callable[[], bool] | None) -> bool:
        """Fit the parameters of ``parts`` ("pupil", "aberrations") to the fit images with the volume and sources fixed:
        :data:`FIT_ITERATIONS` Adam steps on the sum of the images' squared relative errors (gains in closed form),
        from the calibration's current values, which are set to the result. False when stopped."""
        cal, model, base = self.calibration, stage.model, self._exit_cache_base
        na = cal.na_scale.detach().clone().requires_grad_("pupil" in parts)
        edge = cal.pupil_edge.detach().clone().requires_grad_("pupil" in parts)
        zern = cal.zernike.detach().clone().requires_grad_("aberrations" in parts)
        groups = []
        if "pupil" in parts:
            groups += [{"params": [na], "lr": FIT_RATES["na_scale"]}, {"params": [edge], "lr": FIT_RATES["pupil_edge"]}]
        if "aberrations" in parts:
            groups.append({"params": [zern], "lr": FIT_RATES["zernike"]})
        opt = torch.optim.Adam(groups, betas=(0.9, 0.99))
        on_pupil = "pupil" in parts or self.parts["pupil"]
        on_aber = "aberrations" in parts or self.parts["aberrations"]
        for _ in range(FIT_ITERATIONS):
            if self._stop_requested(should_stop):
                return False
            opt.zero_grad(set_to_none=True)
            for idx, per in cache:
                over = dict(base)
                if on_pupil:
                    over.update(na=stage.optics.na * na, pupil_edge=torch.abs(edge))
                if on_aber:
                    over["zernike"] = zern
                src = stage.stage_sources(cal.calibrated_sources()[idx]).detach()
                pred = None
                for lam, w, exit_spec, spec0 in per:
                    img = model.intensity_from_exit(exit_spec, spec0, src, wavelength_um=lam, **over) * w
                    pred = img if pred is None else pred + img
                measured = stage.images[idx]
                g = least_squares_gain(pred, measured)
                resid = (g.reshape(-1, 1, 1) * pred - measured).square().sum(dim=(-2, -1))
                loss = (resid / measured.square().sum(dim=(-2, -1)).clamp_min(1e-30)).sum()
                loss.backward()
            opt.step()
        with torch.no_grad():
            cal.na_scale.copy_(na)
            cal.pupil_edge.copy_(edge)
            cal.zernike.copy_(zern)
        return True

    def _run_stages(self, should_stop: Callable[[], bool] | None, checkpoint_dir: str | Path | None) -> Iterator[Snapshot]:
        """The stages from the first not yet completed (the body of :meth:`run`)."""
        cfg = self.config
        torch.manual_seed(cfg.seed + self.completed_stages)
        global_it = sum(s.iterations for s in cfg.stages[: self.completed_stages])
        self._share_per_source_rows()
        for si in range(self.completed_stages, len(cfg.stages)):
            stage = self._build_stage(si)
            self._carry_volume_to(stage)
            mask = self._loss_mask(stage)
            if not self.calibration.gain_initialised:
                self._init_gains(stage, mask)
            self.calibration.set_trainable(si)
            vol_opt = torch.optim.Adam([self.volume.x], lr=cfg.lr_ri, betas=(0.9, 0.99))
            batch_size = cfg.stage_batch(si)
            data_range = float(stage.images.max())
            record = self._record(stage)
            best = BestIterate(tolerance=cfg.early_stopping_tolerance)
            t0 = time.perf_counter()
            if self.tv_choice is None and tv_is_auto(cfg) and si in selection_stages(cfg):
                yield from self._choose_tv(stage, mask, batch_size, data_range, global_it, should_stop)
                return  # the pilot (run) ends here and starts the run again with the choice
            choose = False  # whether the "auto" parts are chosen at the end of this stage
            if (self.parts_choice is None or self._choose_again) and si == parts_stage(cfg):
                if stage.envelope:  # the parts belong to the multi-slice model: nothing to choose on this run's stages
                    self.apply_parts_choice(PartsChoice(dict(self.parts), {p: "not chosen: no multi-slice stage" if p in self._auto_parts
                                                                        else self._parts_chosen_by[p] for p in PARTS}))
                else:
                    choose = True
                    stage_start = self._capture_branch(), global_it
            while True:  # a second pass when the choice of parts switched some on
                if len(self.validation_indices) and cfg.early_stopping != "off":
                    # The stage's starting volume is a candidate too: a stage that only makes the held-out images worse
                    # ends where it began (from stage 0 on: never a volume that explains them worse than no object).
                    self._track_validation(stage, mask, best, 0)
                terms: dict = {}
                train_error = None
                it = 0
                for it in range(1, stage.iterations + 1):
                    if self._stop_requested(should_stop):
                        self.elapsed_s += time.perf_counter() - t0
                        return
                    progress = global_it / max(1, cfg.total_iterations)
                    snapshot_due = it == stage.iterations or it % cfg.snapshot_every == 0
                    if si == len(cfg.stages) - 1:
                        for group in vol_opt.param_groups:
                            group["lr"] = cfg.lr_ri * final_step_scale(it, stage.iterations, cfg.lr_ri_final_ratio)
                    terms, err = self._step(stage, mask, vol_opt, batch_size, data_range, progress, snapshot_due)
                    train_error = err if snapshot_due else train_error
                    global_it += 1
                    if it == stage.iterations:
                        break
                    if it % cfg.snapshot_every == 0:
                        val = self._track_validation(stage, mask, best, it)
                        snap = self._snapshot(stage, it, global_it, terms, t0, False, val, train_error)
                        paused = time.perf_counter()
                        yield snap
                        t0 += time.perf_counter() - paused  # time spent by the consumer is not the solver's
                        if cfg.early_stopping == "stop" and best.stalled(cfg.early_stopping_patience):
                            record.stopped_at = it
                            global_it += stage.iterations - it  # progress and later stages' numbering as if it had run
                            break
                val = self._end_on_best(stage, mask, best, it, record)
                if not choose:
                    break
                choose = False
                chosen = self._choose_parts(stage, mask, should_stop)
                if chosen is None:
                    self.elapsed_s += time.perf_counter() - t0
                    return
                self.parts_choice.iteration = it
                if not any(self.parts[p] for p in self._auto_parts):
                    break
                if cfg.parts_rerun == "stages" and self.parts_choice.rerun is None:
                    # Parts the data needs: every stage again from the first with them on (run() goes on).
                    self.elapsed_s += time.perf_counter() - t0
                    self._restart_with_parts()
                    return
                # Parts the data needs: the stage again from its start, with them on from the fitted values.
                fitted = {name: getattr(self.calibration, name).detach().clone() for name in ("na_scale", "pupil_edge", "zernike")}
                self._restore_branch(stage_start[0])
                self.calibration.restore_values(fitted)
                global_it = stage_start[1]
                stage, mask = chosen, self._loss_mask(chosen)
                self.calibration.set_trainable(si)
                vol_opt = torch.optim.Adam([self.volume.x], lr=cfg.lr_ri, betas=(0.9, 0.99))
                data_range = float(stage.images.max())
                best = BestIterate(tolerance=cfg.early_stopping_tolerance)
                record.stopped_at = None
            snap = self._complete_stage(stage, record, global_it, terms, t0, val, train_error)
            if checkpoint_dir is not None and (self.group is None or self.group.is_writer):
                self.save_checkpoint(checkpoint_path(checkpoint_dir, si))
            yield snap

    # -- automatic regularisation ---------------------------------------------------------------
    def _choose_tv(self, stage: Stage, mask: torch.Tensor | None, batch_size: int, data_range: float, global_it: int,
                   should_stop: Callable[[], bool] | None) -> Iterator[Snapshot]:
        """Try every weight of the TV path from the stage's starting state and set :attr:`tv_choice` to the one the
        held-out images prefer (:mod:`napari_fdt.recon.regularisation`); left None when stopped (cancelled) meanwhile.
        Yields a snapshot after each weight. The state is then a trial's: the pilot (:meth:`_pilot`) starts the run again."""
        cfg = self.config
        t0 = time.perf_counter()
        n_probe = probe_iterations(stage.iterations)
        start = self._capture_branch()
        trials = []
        for k, tau in enumerate(TV_PATH):
            t1 = time.perf_counter()
            self._restore_branch(start)
            xy, z = candidate_weights(cfg, tau)
            self.loss_weights = dataclasses.replace(self.loss_weights, tv_xy=xy, tv_z=z)
            vol_opt = torch.optim.Adam([self.volume.x], lr=cfg.lr_ri, betas=(0.9, 0.99))
            for it in range(n_probe):
                if self._stop_requested(should_stop):
                    return
                terms, train_error = self._step(stage, mask, vol_opt, batch_size, data_range,
                                                (global_it + it) / max(1, cfg.total_iterations), it == n_probe - 1)
            err, each = self._validation(stage, mask, per_image=True)
            trials.append({"tau": tau, "tv_xy_weight": xy, "tv_z_weight": z, "validation_error": err, "image_errors": each})
            snap = self._snapshot(stage, n_probe, global_it + n_probe, terms, t1, False, err, train_error, trial=k)
            self.elapsed_s += time.perf_counter() - t1  # (the pilot sets the run's time when it ends)
            yield snap
        win = pick(trials)
        self.tv_choice = TVChoice(win["tv_xy_weight"], win["tv_z_weight"], stage=stage.index, probe_iterations=n_probe,
                                  trials=trials, seconds=time.perf_counter() - t0)

    def _capture_branch(self) -> dict[str, Any]:
        """A full copy of what training changes (volume, calibration and its optimiser, batch order), to start
        several candidates from one state."""
        return {**self._capture(), "cal_opt": copy.deepcopy(self.calibration.optimiser.state_dict()),
                "batches": copy.deepcopy(self.batches.state_dict())}

    def _restore_branch(self, state: dict[str, Any]) -> None:
        """Return to a :meth:`_capture_branch` (copies again, so the state can be restored more than once)."""
        self._restore(state, keep_bookkeeping=True)
        self.calibration.optimiser.load_state_dict(copy.deepcopy(state["cal_opt"]))
        self.batches.load_state_dict(copy.deepcopy(state["batches"]))

    # -- per-stage set-up -----------------------------------------------------------------------
    def _build_stage(self, stage_index: int) -> Stage:
        """Stage ``stage_index``'s model and images, with its window planned for the current sources."""
        cfg = self.config
        sc = cfg.stages[stage_index]
        return build_stage(stage_index, sc.factor, sc.iterations, self.acquisition.optics, self.images,
                           self.calibration.sources_um(), device=self.device,
                           coarse_model=self.coarse_model, backward_mode=cfg.backward_mode,
                           obliquity="per_source" if self.parts["obliquity"] else "none",
                           **{**camera_model_options(cfg, self.acquisition), "pixel_integration": self.parts["pixel_integration"]})

    def _carry_volume_to(self, stage: Stage) -> None:
        """Make the RI grid on the stage's grid (first stage) or resample it there from the previous stage's."""
        cfg = self.config
        h, w = stage.grid_shape
        if self.volume is None:
            self.volume = RIVolume((self.acquisition.optics.n_slices, h, w), delta_n_max=cfg.delta_n_max,
                                   activation=cfg.activation, device=self.device, dtype=self.dtype)
        elif self.volume_factor != stage.factor:
            self.volume.resample(self.volume_factor, stage.factor, self.full_shape)
        self.volume_factor = stage.factor

    def _loss_mask(self, stage: Stage) -> torch.Tensor | None:
        """(N, h, w) 0/1 pixels the loss compares: the envelope model's coverage times the coherence masks (None: all)."""
        cfg = self.config
        mask = stage.coverage
        if cfg.coherence in ("mask", "mask+spectral"):
            cm = coherence_masks(stage.model, stage.stage_sources(self.calibration.calibrated_sources().detach()),
                                 threshold=cfg.mask_threshold, wavelengths_um=self.wavelengths, weights=self.weights)
            mask = cm if mask is None else mask * cm
        return mask

    def _init_gains(self, stage: Stage, mask: torch.Tensor | None) -> None:
        """Start each image's gain at its least-squares fit to the homogeneous-medium prediction (at least 1e-6)."""
        n = self.acquisition.n_images
        zero = torch.zeros((self.acquisition.optics.n_slices, *stage.image_shape), device=self.device, dtype=self.dtype)  # field grid
        gains = torch.empty(n, device=self.device, dtype=self.dtype)
        with torch.no_grad():
            for sl in iter_batches(n, self.config.batch_size):
                idx = torch.arange(sl.start, sl.stop, device=self.device)
                src = stage.stage_sources(self.calibration.calibrated_sources()[idx])
                pred = spectral_images(stage.model, zero, src, None, self.wavelengths, self.weights)
                gains[idx] = least_squares_gain(pred, stage.images[idx], None if mask is None else mask[idx]).clamp_min(1e-6)
        self.calibration.set_gains(gains)

    def _record(self, stage: Stage) -> StageRecord:
        """The stage's entry in :attr:`stages` (replacing one of a cancelled attempt)."""
        o = self.acquisition.optics
        record = StageRecord(stage.index, stage.factor, stage.field_factor, (o.n_slices, *stage.grid_shape), stage.window,
                             stage.optics.na, stage.iterations, model="envelope" if stage.envelope else "multislice")
        self.stages = [r for r in self.stages if r.stage != stage.index] + [record]
        return record

    # -- one iteration --------------------------------------------------------------------------
    def _stop_requested(self, should_stop: Callable[[], bool] | None) -> bool:
        """``should_stop()`` (on any rank, in a distributed run: every rank stops together)."""
        if should_stop is None:
            return False
        return self.group.any(should_stop()) if self.group else should_stop()

    def _step(self, stage: Stage, mask: torch.Tensor | None, vol_opt: torch.optim.Optimizer, batch_size: int,
              data_range: float, progress: float, with_error: bool = False) -> tuple[dict[str, torch.Tensor], float | None]:
        """One iteration: next batch, prediction, loss, gradients (summed over ranks), one step of both optimisers.

        Returns the loss terms (tensors, unweighted; this rank's part of the data terms in a distributed run) and,
        with ``with_error`` (snapshots only: it waits for the device), the training images' relative error (None
        otherwise and for a rank with no training image in the batch).
        """
        idx = self.batches.next(batch_size)
        dn = self.volume.delta_n()
        share = None
        if self.group is not None:  # this rank's images of the batch, normalised by the whole batch
            share = BatchShare.of_batch(None if mask is None else mask[idx], (len(idx), *stage.images.shape[1:]),
                                        regularisers=self.group.is_writer)
            idx = self.group.local(idx)
        held = self._held_out[idx] if len(self.validation_indices) else None
        if held is not None and bool(held.any()):  # held-out images last, through a constant volume and shared calibration
            idx = torch.cat([idx[~held], idx[held]])
            n_train = int((~held).sum())
            pred = torch.cat([self._predict_normalised(stage, dn, idx[:n_train]),
                              self._predict_normalised(stage, dn, idx[n_train:], held_out=True)])
        else:
            n_train = len(idx)
            # A rank with no image in this batch predicts none (and still joins the gradient sum).
            pred = self._predict_normalised(stage, dn, idx) if len(idx) else stage.images[idx]
        m = None if mask is None else mask[idx]
        loss, terms = total_loss(pred, stage.images[idx], dn, self.loss_weights, progress, mask=m,
                                 data_range=data_range, share=share)
        cal_opt = self.calibration.optimiser
        vol_opt.zero_grad(set_to_none=True)
        cal_opt.zero_grad(set_to_none=True)
        if loss.requires_grad:
            loss.backward()
        if self.group is not None:
            self.group.reduce_gradients([self.volume.x, *self.calibration.shared_parameters()],
                                        self.calibration.per_source_parameters())
        vol_opt.step()
        cal_opt.step()
        train_error = None
        if with_error and n_train:
            train_error = relative_image_error(pred[:n_train].detach(), stage.images[idx[:n_train]], None if m is None else m[:n_train])
        return terms, train_error

    def _predict_normalised(self, stage: Stage, dn: torch.Tensor, idx: torch.Tensor, held_out: bool = False) -> torch.Tensor:
        """Images (B, h_f, w_f) of images ``idx`` (B,) on the stage's field grid, in normalised units, differentiable.

        ``dn``: Δn on the stage grid (n_slices, h, w). Each image's position and gain are its own rows; depth also
        moves through the common offset. ``held_out``: the volume and the shared calibration enter as constants, so
        these images' loss fits their own rows only (validation images).
        """
        cal = self.calibration
        src = stage.stage_sources(cal.calibrated_sources(shared_frozen=held_out)[idx])
        gain = torch.exp(cal.log_gain[idx])
        field_dn = stage.to_field_grid(dn.detach() if held_out else dn)
        return spectral_images(stage.model, field_dn, src, gain, self.wavelengths, self.weights,
                               **cal.optics_overrides(stage.optics, stage.envelope, shared_frozen=held_out))

    # -- validation -------------------------------------------------------------------------------
    def validation_error(self, stage: Stage, mask: torch.Tensor | None = None) -> float | None:
        """Relative RMS error of the held-out images at ``stage`` (None without a validation split).

        Predicted through the current volume with their positions as fitted to their own images (a fit that never
        reaches the volume) and their gains refitted in closed form; ``mask`` (N, h_f, w_f) as the loss's. Every
        rank computes the same number (no collective; in a distributed run after the rows are shared).
        """
        out = self._validation(stage, mask)
        return None if out is None else out[0]

    def _validation(self, stage: Stage, mask: torch.Tensor | None, per_image: bool = False) -> tuple[float, list[float]] | None:
        """(validation error, each held-out image's error (empty unless asked)); None without a split."""
        held = self.validation_indices
        if not len(held):
            return None
        with torch.no_grad():  # the gains they carry are refitted: the fit is invariant to a scale per image
            dn = self.volume.delta_n()
            preds = [self._predict_normalised(stage, dn, torch.as_tensor(held[sl], device=self.device))
                     for sl in iter_batches(len(held), self.config.batch_size)]
        idx = torch.as_tensor(held, device=self.device)
        pred, measured, m = torch.cat(preds), stage.images[idx], None if mask is None else mask[idx]
        each = per_image_errors(pred, measured, m, fit_gain=True) if per_image else []
        return relative_image_error(pred, measured, m, fit_gain=True), each

    def _track_validation(self, stage: Stage, mask: torch.Tensor | None, best: BestIterate, it: int) -> float | None:
        """The validation error now, recorded in ``best`` (with a copy of the state when it is the lowest yet)."""
        val = self.validation_error(stage, mask)
        if val is not None and self.config.early_stopping != "off":
            best.update(it, val, self._capture)
        return val

    def _end_on_best(self, stage: Stage, mask: torch.Tensor | None, best: BestIterate, it: int, record: StageRecord) -> float | None:
        """The stage's final validation error; with early stopping, first return to the stage's best iterate when the
        last one is worse than it by more than the tolerance. Fills the record's validation fields."""
        val = self._track_validation(stage, mask, best, it)
        record.best_iteration = it
        if val is not None and self.config.early_stopping != "off" and val > best.best_error * (1.0 + best.tolerance):
            self._restore(best.state, keep_bookkeeping=True)
            val, record.best_iteration = best.best_error, best.best_iteration
        record.validation_error = val
        return val

    # -- end of a stage, snapshots ----------------------------------------------------------------
    def _complete_stage(self, stage: Stage, record: StageRecord, global_it: int, terms: dict, t0: float,
                        validation_error: float | None, train_error: float | None) -> Snapshot:
        """Close the stage's record and time, take its snapshot and remember it as the last complete state."""
        record.seconds = time.perf_counter() - t0
        snap = self._snapshot(stage, stage.iterations, global_it, terms, t0, True, validation_error, train_error)
        self.elapsed_s += record.seconds
        snap.elapsed_s = self.elapsed_s
        self.completed_stages = stage.index + 1
        self.last_complete = snap
        self._last_complete_state = self._capture()
        self.final_losses = snap.losses
        return snap

    def _stage_cost(self, factor: int) -> float:
        """Rough relative cost of an iteration at a stage factor (grid area the model works on)."""
        from napari_fdt.recon.stages import field_factor

        g = factor if (factor > 1 and self.coarse_model == "envelope") else field_factor(self.acquisition.optics, factor)
        h, w = self.full_shape
        return (h / g) * (w / g)

    def _snapshot(self, stage: Stage, it: int, global_it: int, terms: dict, stage_t0: float, complete: bool,
                  validation_error: float | None = None, train_error: float | None = None, trial: int | None = None) -> Snapshot:
        """The snapshot now (``trial``: the index in the TV path of the weight the pilot has just tried)."""
        cfg = self.config
        rerun_with = self._rerun_parts()
        phase = TV_CHOICE if self._piloting else (RERUN if rerun_with else RUN)
        terms = self._gather(terms, optimiser_state=complete)
        now = time.perf_counter()
        elapsed = self.elapsed_s + (now - stage_t0)
        per_it = (now - stage_t0) / max(it, 1)
        left, later = work_left(cfg, phase, stage.index, it, trial)
        remaining = left * per_it
        cur_cost = self._stage_cost(stage.factor)
        for iterations, factor in later:
            remaining += iterations * per_it * self._stage_cost(factor) / cur_cost
        losses = as_floats(terms) if terms else {}
        snap = Snapshot(
            stage=stage.index, n_stages=len(cfg.stages), factor=stage.factor, iteration=it,
            stage_iterations=stage.iterations, global_iteration=global_it, total_iterations=cfg.total_iterations,
            delta_n=self.volume.delta_n().detach().cpu().numpy().astype(np.float32),
            sources_um=self.sources_um(), gains=self.gains(),
            calibration=self.calibration.summary(), losses=losses, elapsed_s=elapsed, eta_s=remaining,
            stage_complete=complete, full_shape=self.full_shape, validation_error=validation_error, train_error=train_error,
            rerun_with=rerun_with, phase=phase, tv_weights=None if trial is None else candidate_weights(cfg, TV_PATH[trial]),
        )
        snap.phase_iteration, snap.phase_iterations = phase_counts(cfg, phase, global_it, trial)
        self.history.append({"stage": stage.index, "iteration": it, "global_iteration": global_it,
                             "elapsed_s": elapsed, **losses, "validation_error": validation_error, "train_error": train_error})
        return snap

    def _rerun_parts(self) -> tuple[str, ...]:
        """The parts kept by the data while the stages run again with them (:attr:`Snapshot.rerun_with`)."""
        choice = self.parts_choice
        if choice is None or choice.rerun != "stages":
            return ()
        return tuple(p for p, on in choice.parts.items() if on and choice.chosen_by.get(p) == "validation")

    # -- distributed ----------------------------------------------------------------------------
    def _share_per_source_rows(self, optimiser_state: bool = False) -> None:
        """Distributed: every rank gets each image's source and gain rows (and their Adam moments) from its owner."""
        if self.group is None:
            return
        self.group.share_rows(self.calibration.per_source_rows(optimiser_state))

    def _gather(self, terms: dict, optimiser_state: bool = False) -> dict:
        """Distributed: the whole batch's loss terms and every image's rows on every rank (a collective).

        The data terms and the total are sums of the ranks' parts; the regularisers are the same on all.
        """
        if self.group is None:
            return terms
        self._share_per_source_rows(optimiser_state)
        return self.group.sum_terms(terms, ("l1", "l2", "ssim_loss", "total")) if terms else terms

    # -- cancel ---------------------------------------------------------------------------------
    def _capture(self) -> dict[str, Any]:
        """Copies of the optimised state (small tensors), to return to after a cancel."""
        return {"x": self.volume.x.detach().clone(), "factor": self.volume_factor, "calibration": self.calibration.copy_values(),
                "elapsed_s": self.elapsed_s, "stages": list(self.stages)}

    def restore_last_complete(self) -> None:
        """Return to the state at the end of the last complete stage (after a cancel mid-stage)."""
        state = getattr(self, "_last_complete_state", None)
        if state is None:
            raise RuntimeError("no stage has completed yet")
        self._restore(state)

    def _restore(self, state: dict[str, Any], keep_bookkeeping: bool = False) -> None:
        """Return the volume and calibration to a :meth:`_capture`; also its stage records and time unless
        ``keep_bookkeeping`` (returning to a stage's best iterate keeps the time spent reaching the last)."""
        with torch.no_grad():
            self.volume.x = state["x"].clone().requires_grad_()
        self.volume_factor = state["factor"]
        self.calibration.restore_values(state["calibration"])
        if not keep_bookkeeping:
            self.stages = list(state["stages"])
            self.elapsed_s = state["elapsed_s"]

    # -- results ------------------------------------------------------------------------------
    def delta_n_full(self) -> np.ndarray:
        """Δn of the current grid on the acquisition grid (n_slices, H, W), float32."""
        if self.volume is None:
            raise RuntimeError("nothing reconstructed yet")
        return self.volume.full_resolution(self.volume_factor, self.full_shape).cpu().numpy().astype(np.float32)

    def ri_full(self) -> np.ndarray:
        """Absolute RI on the acquisition grid (n_slices, H, W), float32."""
        return (self.acquisition.optics.n_background + self.delta_n_full()).astype(np.float32)

    def sources_um(self) -> np.ndarray:
        """(N, 3) calibrated source positions (depth offset applied), float64, µm, acquisition coordinates."""
        return self.calibration.sources_um()

    def gains(self) -> np.ndarray:
        """(N,) calibrated gains in the acquisition's intensity units per model unit, float64."""
        return self.calibration.gains() * self.image_scale

    def evaluation_stage(self) -> Stage:
        """The multi-slice model on the acquisition grid (factor 1) for the current calibrated sources (for :meth:`predict`)."""
        return build_stage(-1, 1, 0, self.acquisition.optics, self.images, self.sources_um(), device=self.device)

    def predict(self, indices: Sequence[int] | np.ndarray | torch.Tensor, stage: Stage | None = None) -> np.ndarray:
        """Images (B, h, w) float32 of images ``indices`` (B,) as the current state predicts them, without autograd.

        In the acquisition's intensity units (calibrated gains, sources and optics applied). ``stage``:
        None (default) is :meth:`evaluation_stage`, the acquisition grid (build it once and pass it when
        predicting many batches); a stage of the run gives images on its field grid, the volume taken at that
        stage's factor (it must be the current grid's factor, or 1).
        """
        if self.volume is None:
            raise RuntimeError("nothing reconstructed yet")
        stage = self.evaluation_stage() if stage is None else stage
        if stage.factor != 1 and stage.factor != self.volume_factor:
            raise ValueError(f"the volume is on a factor-{self.volume_factor} grid; predict on a stage of factor "
                             f"{self.volume_factor} or 1, not {stage.factor}")
        idx = torch.as_tensor(indices if isinstance(indices, torch.Tensor) else np.asarray(indices, dtype=np.int64),
                              dtype=torch.long).reshape(-1).to(self.device)
        with torch.no_grad():
            dn = self.volume.full_resolution(self.volume_factor, self.full_shape) if stage.factor == 1 else self.volume.delta_n()
            return (self._predict_normalised(stage, dn, idx) * self.image_scale).cpu().numpy()

    # -- checkpoints ----------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """The checkpoint's content (:func:`napari_fdt.recon.checkpoint.checkpoint_state`)."""
        return checkpoint_state(self)

    def save_checkpoint(self, path: str | Path) -> Path:
        """Write the state atomically (temporary file, then rename)."""
        return write_checkpoint(self.state_dict(), path)

    @classmethod
    def from_checkpoint(cls, path: str | Path, acquisition: Acquisition, *, device: str | torch.device = "auto",
                        group: Group | None = None) -> "Reconstructor":
        """Resume: the next :meth:`run` continues with the first stage the checkpoint had not completed."""
        state = read_checkpoint(path, acquisition)
        rec = cls(acquisition, SolverConfig.from_dict(state["config"]), device=device, initial_sources_um=state["initial_sources_um"],
                  group=group)
        restore_checkpoint(rec, state)
        return rec


def envelope_stages(config: SolverConfig, coarse_model: str) -> frozenset[int]:
    """Stages that run the envelope model: factor > 1 with ``coarse_model`` ``"envelope"`` (as :func:`build_stage`)."""
    if coarse_model != "envelope":
        return frozenset()
    return frozenset(i for i, s in enumerate(config.stages) if s.factor > 1)


def _envelope_stages_before_multislice(config: SolverConfig, coarse_model: str) -> frozenset[int]:
    """The envelope stages that a multi-slice stage follows (none when every stage is an envelope one)."""
    env = envelope_stages(config, coarse_model)
    return frozenset(i for i in env if not all(j in env for j in range(i, len(config.stages))))


def position_frozen_stages(config: SolverConfig, coarse_model: str) -> frozenset[int]:
    """Stages whose source positions and depth offset stay fixed: with ``calibrate_sources_in_envelope_stages`` off, the
    envelope stages (factor > 1, ``coarse_model`` ``"envelope"``) that a multi-slice stage follows. Fitted with the volume
    at the truth, the envelope model pulls the positions off (``docs/solver.md``, "Source positions")."""
    if config.calibrate_sources_in_envelope_stages:
        return frozenset()
    return _envelope_stages_before_multislice(config, coarse_model)


def depth_frozen_stages(config: SolverConfig, coarse_model: str) -> frozenset[int]:
    """Stages whose source depths (each source's own and the common offset) stay fixed while x, y train: with
    ``calibrate_source_depth_in_envelope_stages`` off, the envelope stages that a multi-slice stage follows."""
    if config.calibrate_source_depth_in_envelope_stages:
        return frozenset()
    return _envelope_stages_before_multislice(config, coarse_model)


def reconstruct(acquisition: Acquisition, config: SolverConfig | None = None, *, device: str = "auto", **kwargs) -> Iterator[Snapshot]:
    """Shortcut: ``Reconstructor(acquisition, config, device=device).run(**kwargs)``."""
    return Reconstructor(acquisition, config, device=device).run(**kwargs)
