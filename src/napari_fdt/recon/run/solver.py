"""The reconstruction: one solver loop, exposed as a generator of snapshots.

``Reconstructor(acquisition, config).run()`` yields a :class:`Snapshot` every ``snapshot_every``
iterations and at the end of every stage (``stage_complete=True``). Stopping the iteration (or calling
``close()`` on the generator) cancels between iterations; :attr:`Reconstructor.last_complete` then holds
the last complete stage. The command line, the napari widgets and the benchmarks all drive this loop.

What is optimised (``docs/solver.md``): the explicit RI grid (:class:`~napari_fdt.recon.problem.volume.RIVolume`), a
log-gain per image, and (from ``calibration_from_stage``) the lateral position of every source, a common
offset of the source plane's depth, and optionally the pixel size and slice spacing as global scales.
The RI grid has its own Adam optimiser, rebuilt at each stage (its moments belong to voxels that the
resampling replaces); the calibration parameters (:class:`~napari_fdt.recon.calibration.calibration.Calibration`) keep
one Adam optimiser for the whole run. One stage's training is :mod:`napari_fdt.recon.loop.stage_loop`'s, the choices
plugged into it :mod:`napari_fdt.recon.choices.plugged`'. Checkpoints are :mod:`napari_fdt.recon.loop.checkpoint`'s, the checks
before a run :mod:`napari_fdt.recon.problem.preflight`'s; the snapshots :mod:`~napari_fdt.recon.loop.snapshot`'s, the trials of the TV
weights :mod:`~napari_fdt.recon.choices.tv_search`'s, the model parts :mod:`~napari_fdt.recon.choices.parts_switch`'s and
:mod:`~napari_fdt.recon.choices.parts_search`'s, the validation error :mod:`~napari_fdt.recon.loop.run_validation`'s.

Given a :class:`~napari_fdt.recon.problem.distributed.Group` (``group=``), the run is one rank of a data-parallel
reconstruction (``docs/distributed.md``): each rank computes the images it owns of every batch, the
gradients of the shared parameters are summed over ranks, and the result equals the single-process one.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator

import numpy as np
import torch

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.data.mapped import mean_of
from napari_fdt.device import resolve_device
from napari_fdt.errors import FDTInputError, FDTWarning
from napari_fdt.model.coherence import coherence_masks, spectral_images
from napari_fdt.model.gain import least_squares_gain
from napari_fdt.model.render import iter_batches
from napari_fdt.recon.assess.validation import BestIterate, holdout_indices, relative_image_error
from napari_fdt.recon.calibration.calibration import Calibration
from napari_fdt.recon.choices.parts_coarse_end import early_test_stage
from napari_fdt.recon.choices.parts_pilot import pilot_due
from napari_fdt.recon.choices.parts_search import choice_errors, fit_images
from napari_fdt.recon.choices.parts_switch import apply_parts_choice, drop_parts_that_do_not_fit, init_parts, tests_again_s
from napari_fdt.recon.choices.plugged import default_choices
from napari_fdt.recon.loop.checkpoint import (
    checkpoint_path,
    checkpoint_state,
    in_stage_path,
    in_stage_state,
    prune_in_stage,
    read_checkpoint,
    restore_checkpoint,
    resume_in_stage,
    write_checkpoint,
)
from napari_fdt.recon.loop.model_parts import FINEST_ONLY_PARTS, PartsChoice
from napari_fdt.recon.loop.pace import Pace
from napari_fdt.recon.loop.phases import RERUN, RUN, TV_CHOICE
from napari_fdt.recon.loop.plan import Phase, Plan, make_plan, stage_phase
from napari_fdt.recon.loop.regularisation import TV_PATH, TVChoice, candidate_weights, selection_stages, tv_is_auto
from napari_fdt.recon.loop.run_state import InState, RunState
from napari_fdt.recon.loop.run_validation import validation_error
from napari_fdt.recon.loop.snapshot import Snapshot, StageRecord, complete_stage, rerun_parts
from napari_fdt.recon.loop.stage_loop import StageWork, Verdict, new_optimiser, train_stage
from napari_fdt.recon.problem.batches import BatchOrder
from napari_fdt.recon.problem.losses import BatchShare, LossWeights, total_loss
from napari_fdt.recon.problem.preflight import check_memory, warn_about_images, warn_about_sampling
from napari_fdt.recon.problem.stage_images import LazyImages
from napari_fdt.recon.problem.stage_roles import depth_frozen_stages, envelope_stages, position_frozen_stages, set_stage_roles
from napari_fdt.recon.problem.stage_spec import StageSpec, stage_spec
from napari_fdt.recon.problem.stages import Stage, build_stage, camera_model
from napari_fdt.recon.problem.volume import RIVolume
from napari_fdt.recon.run.results import RunResults
from napari_fdt.recon.settings.config import SolverConfig, resolve_coarse_model, resolve_stage_lengths
from napari_fdt.recon.settings.schedule import final_step_scale

if TYPE_CHECKING:
    from napari_fdt.recon.problem.distributed import Group

# Snapshot and StageRecord (recon.snapshot) and the stage roles (recon.stage_roles) are re-exported: callers import them from here.
__all__ = ["Snapshot", "StageRecord", "Reconstructor", "reconstruct", "envelope_stages", "position_frozen_stages", "depth_frozen_stages"]


class Reconstructor(RunResults):
    """A reconstruction of one acquisition with one configuration.

    Parameters
    ----------
    acquisition: the data.
    config: solver settings.
    device: ``"auto"``, ``"cpu"`` or ``"cuda"``.
    initial_sources_um: (N, 3) start positions; default the acquisition's ``sources_um``, else the
        2D-Gaussian fit of :mod:`napari_fdt.recon.calibration.source_fit` (with ``config.source_depth_um`` if given).
    group: this process's rank in a data-parallel run (:func:`napari_fdt.recon.problem.distributed.setup`), None for
        one process. Every rank must then iterate :meth:`run` in step (it holds collectives); only rank 0
        writes checkpoints.

    Results: :meth:`delta_n_full` / :meth:`ri_full` (the volume), :meth:`sources_um` and :meth:`gains` (the
    calibration), :meth:`predict` (images of the current state, in the acquisition's units).
    """

    # the run's state (:class:`~napari_fdt.recon.loop.run_state.RunState`), read and written as attributes
    calibration, batches, volume, volume_factor = InState(), InState(), InState(), InState()
    completed_stages, stages, history, elapsed_s, final_losses = InState(), InState(), InState(), InState(), InState()
    tv_choice, parts_choice, early_trials, last_complete, last_complete_state = InState(), InState(), InState(), InState(), InState()

    def __init__(
        self,
        acquisition: Acquisition,
        config: SolverConfig | None = None,
        *,
        device: str | torch.device = "auto",
        initial_sources_um: np.ndarray | None = None,
        group: Group | None = None,
    ) -> None:
        self.acquisition, self.group = acquisition, group
        #: the configuration as given (what RI.json and checkpoints store: resolving it again gives the same run)
        self.requested_config = config or SolverConfig()
        if self.requested_config.tv_family == "true":  # several whole runs (recon/run/family.py), never one solver's
            raise FDTInputError("tv_family", "asks for a family of runs, not one run", "use fdt reconstruct --tv-family or napari_fdt.recon.run.family.run_family")
        #: the configuration as run: the finest stage lengthened to ``final_stage_min_passes`` passes over the images
        #: (:func:`napari_fdt.recon.settings.config.resolve_stage_lengths`)
        self.config = resolve_stage_lengths(self.requested_config, acquisition.n_images)
        self.device, self.dtype = resolve_device(device), torch.float32
        cfg = self.config
        #: the coarse stages' model after resolving "auto" for this device
        self.coarse_model = resolve_coarse_model(cfg.coarse_model, self.device.type)
        #: the stage models' pupil edge and pixel integration as stated or needed, resolved once (the parts may add the latter)
        self.camera = camera_model(cfg, acquisition)
        n_img = acquisition.n_images
        if initial_sources_um is None:
            if acquisition.sources_um is not None:
                initial_sources_um = acquisition.sources_um
            else:
                from napari_fdt.recon.calibration.source_fit import initial_sources

                initial_sources_um, self.source_fit_report = initial_sources(
                    acquisition, depth_um=cfg.source_depth_um, device=self.device
                )
        src = np.asarray(initial_sources_um, dtype=np.float64)
        if src.shape != (n_img, 3):
            raise FDTInputError("sources_um", f"need one [x, y, depth] per image ({n_img}), got shape {src.shape}",
                                "give one source per image")
        self.initial_sources_um = src.copy()
        mean = mean_of(acquisition.images)
        if not mean > 0:
            raise FDTInputError("images", "are all zero (or their mean is not positive)", "check the acquisition")
        #: the acquisition's mean intensity; the solver works on images divided by it
        self.image_scale = mean
        warn_about_images(acquisition)
        warn_about_sampling(acquisition, src)  # before any run
        #: (N, H, W) float32 images / image_scale, read batch by batch from the acquisition's array (no float32 copy of
        #: the stack on the CPU: :mod:`napari_fdt.recon.problem.stage_images`); each stage averages them to its grid
        self.images = LazyImages(acquisition.images, mean)
        self.full_shape = acquisition.image_shape
        #: everything the run changes and has decided (:mod:`napari_fdt.recon.loop.run_state`; its fields read as attributes here)
        self.state = RunState(self._new_calibration(), BatchOrder(n_img, cfg.seed, self.device))
        #: (V,) indices of the held-out images, spread over the field (empty: no validation). They are drawn in
        #: batches like the others, but their loss reaches only their own position and gain: never the volume
        #: nor the shared calibration (a fit of their positions that does not touch the volume).
        self.validation_indices = holdout_indices(src, cfg.validation_fraction)
        self._held_out = np.zeros(n_img, dtype=bool)  # in host memory: a batch is split without a device sync
        self._held_out[np.asarray(self.validation_indices, dtype=np.int64)] = True
        #: the optional model parts (:mod:`napari_fdt.recon.loop.model_parts`) as now switched; "auto" ones are off until chosen
        self.parts: dict[str, bool] = {}
        self.wavelengths, self.weights = None, None
        #: auto parts the finest stage chooses again after every stage ran again with the kept ones (``parts_rerun``)
        self._choose_again: list[str] = []
        #: the choices plugged into every stage (:mod:`napari_fdt.recon.choices.plugged`)
        self.choices = default_choices()
        init_parts(self)
        self.loss_weights = LossWeights.from_config(cfg)
        if tv_is_auto(cfg):  # until the choice: the path's smallest weight (what the stages before the trials run with)
            xy, z = candidate_weights(cfg, TV_PATH[0])
            self.loss_weights = dataclasses.replace(self.loss_weights, tv_xy=xy, tv_z=z)
        if tv_is_auto(cfg) and not len(self.validation_indices):
            warnings.warn("tv_xy_weight: \"auto\" chooses the TV weights by the validation error, and this run holds no "
                          "images out (validation_fraction 0, or too few images): the smallest weights of the path are used "
                          f"(tau_xy {xy:g}, tau_z {z:g}). Give validation_fraction > 0 or fixed weights", FDTWarning, stacklevel=2)
            self.tv_choice = TVChoice(xy, z, stage=0, probe_iterations=0, reason="no validation split")
        check_memory(acquisition, cfg, src, self.device, len(self.wavelengths) if self.wavelengths else 1)
        drop_parts_that_do_not_fit(self, src)
        self._make_plan()

    # -- the plan ---------------------------------------------------------------------------------
    def _make_plan(self) -> None:
        """The run's plan (:mod:`napari_fdt.recon.loop.plan`) from where it stands: the TV trials in the selection stage while
        the weights are still to choose, the stages again when a kept part makes them run again. Sets :attr:`plan` and
        :attr:`pace`."""
        choose_tv_at = None
        if self.tv_choice is None and tv_is_auto(self.config) and min(selection_stages(self.config)) >= self.completed_stages:
            choose_tv_at = min(selection_stages(self.config))
        #: the phases of the run, known before its first iteration (revised when a choice adds or shortens phases)
        self.plan = make_plan(self.config, self.acquisition.optics, self.full_shape, self.initial_sources_um, self.coarse_model,
                              self.device.type, choose_tv_at, pixel_integration=self.parts["pixel_integration"],
                              parts_to_choose=self.parts_choice is None, pupil_edge=self.camera.pupil_edge,
                              finest_parts=tuple(p for p in FINEST_ONLY_PARTS if p in self._auto_parts), pupil_pilot=self.completed_stages == 0 and pilot_due(self),
                              early_test_stage=early_test_stage(self), auto_parts=tuple(self._auto_parts),
                              n_images=self.acquisition.n_images, n_held=len(self.validation_indices))
        #: the time-left estimate from the plan and the measured times
        self.pace = Pace(self.plan)
        #: the index in :attr:`plan` of the phase now running
        self._phase_index = 0
        if rerun_parts(self):  # (resumed in the stages run again with kept parts)
            self._add_rerun_phases()

    def _revise_plan(self, plan: Plan) -> None:
        """Take a revised plan (phases appended or shortened); the measured times so far stay."""
        self.plan = plan
        self.pace.plan = plan

    def _stage_phase(self, stage: int, pass_name: str, parts: tuple[str, ...]) -> Phase:
        """The plan's phase of stage ``stage`` as this run makes it, with the model ``parts`` on."""
        return stage_phase(self.config, self.acquisition.optics, self.full_shape, self.initial_sources_um, stage, self.coarse_model,
                           self.device.type, pass_name, parts, self.parts["pixel_integration"], self.camera.pupil_edge)

    def _add_rerun_phases(self) -> None:
        """Append every stage again, as the kept parts make them run (with their coarse model); once."""
        if any(p.pass_name == RERUN and p.stage == 0 for p in self.plan.phases):
            return
        again = [self._stage_phase(i, RERUN, rerun_parts(self)) for i in range(len(self.config.stages))]
        tests = tests_again_s(self, rerun_parts(self)) if self._auto_parts else None
        self._revise_plan(self.plan.with_rerun(again, tests_s=tests))

    def _enter_stage_phase(self, stage_index: int) -> None:
        """Make the phase of stage ``stage_index`` in this pass the current one: a stage before the TV trials (while the
        weights are to choose), of the run, or of the stages run again with kept parts."""
        if self.tv_choice is None and self.plan.has(TV_CHOICE, stage_index):
            self._phase_index = self.plan.index(TV_CHOICE, stage_index)
        else:
            self._phase_index = self.plan.index(RERUN if rerun_parts(self) else RUN, stage_index)

    # -- the algorithm --------------------------------------------------------------------------
    def run(self, should_stop: Callable[[], bool] | None = None, checkpoint_dir: str | Path | None = None) -> Iterator[Snapshot]:
        """Run the remaining stages, yielding snapshots. ``should_stop()`` is polled between iterations.

        Per stage (:mod:`napari_fdt.recon.loop.stage_loop`): build the stage's model and images for the current sources,
        carry the volume to its grid, make the loss mask, start the gains (once), switch the calibration on or off;
        then the choices at its start, its iterations (batch, predict, loss, step; a snapshot every
        ``snapshot_every``), the choices at its end; it ends with a snapshot and a checkpoint
        (``checkpoint_dir/stage_<i>.pt``). The choices (:mod:`napari_fdt.recon.choices.plugged`: the ``"auto"`` TV weights at
        the selection stage, the ``"auto"`` model parts after the first multi-slice stage) may send the run back to
        its first stage where what they chose changes what the stages before did.
        """
        #: the solver's compute seconds (elapsed_s: the consumer's pauses not counted) at the last checkpoint
        self._checkpoint_dir, self._checkpointed_s = checkpoint_dir, self.elapsed_s
        self._start_pass()
        while self.completed_stages < len(self.config.stages):
            work = self._begin_stage(self.completed_stages)
            verdict = yield from train_stage(self, work, self.choices, should_stop)
            if verdict is not Verdict.GO_ON:
                self.elapsed_s += time.perf_counter() - work.t0
                if verdict is Verdict.STOPPED:
                    return
                self._start_pass()  # FROM_FIRST_STAGE: the choice has set the state back
                continue
            yield self._end_stage(work)

    def _start_pass(self) -> None:
        """Before the stages run from the first not completed: the seed (as a run from there would set it) and, in a
        distributed run, every image's rows from its owner."""
        torch.manual_seed(self.config.seed + self.completed_stages)
        self._share_per_source_rows()

    def _restart(self, keep_last_complete: bool = False) -> None:
        """Back to the state before any stage ran (volume, calibration and its optimiser, batch order, records); with
        ``keep_last_complete`` the last complete stage stays what a cancel returns to until a stage completes again."""
        self.state = self.state.fresh(self._new_calibration(), BatchOrder(self.acquisition.n_images, self.config.seed, self.device),
                                      keep_last_complete)

    def _new_calibration(self) -> Calibration:
        """The calibration parameters at their start (the initial sources, the acquisition's optics)."""
        cal = Calibration(self.initial_sources_um, self.config, self.acquisition.optics, device=self.device, dtype=self.dtype,
                          pupil_edge=self.camera.pupil_edge)
        if getattr(self, "parts", None):
            cal.fit_pupil, cal.fit_aberrations = self.parts["pupil"], self.parts["aberrations"]
        set_stage_roles(cal, self.config, self.coarse_model)
        return cal

    # -- optional model parts (:mod:`napari_fdt.recon.choices.parts_switch`, :mod:`napari_fdt.recon.choices.parts_search`) -------------
    def apply_parts_choice(self, choice: PartsChoice) -> None:
        """Take a choice of parts (made here, or read from a checkpoint): :func:`napari_fdt.recon.choices.parts_switch.apply_parts_choice`."""
        apply_parts_choice(self, choice)
        if choice.rerun == "stages" and getattr(self, "plan", None) is not None:  # the plan holds the stages run again
            self._add_rerun_phases()

    def _choice_errors(self, stage: Stage, mask: torch.Tensor | None) -> tuple[float, list[float]]:
        """The parts' paired test's errors: :func:`napari_fdt.recon.choices.parts_search.choice_errors`."""
        return choice_errors(self, stage, mask)

    def _fit_images(self) -> torch.Tensor:
        """The training images the pupil parts are fitted to: :func:`napari_fdt.recon.choices.parts_search.fit_images`."""
        return fit_images(self)

    # -- a stage's start and end -------------------------------------------------------------------
    def _begin_stage(self, stage_index: int) -> StageWork:
        """Stage ``stage_index``'s model and images, the volume on its grid, its loss mask, the gains (once), the
        calibration's switches, a new RI optimiser; its record and its phase in the plan."""
        cfg = self.config
        stage = self._build_stage(stage_index)
        self._carry_volume_to(stage)
        mask = self._loss_mask(stage)
        if not self.calibration.gain_initialised:
            self._init_gains(stage, mask)
        self.calibration.set_trainable(stage_index)
        self._enter_stage_phase(stage_index)
        work = StageWork(stage, mask, new_optimiser(self), cfg.stage_batch(stage_index), float(stage.images.max()),
                         self._record(stage), BestIterate(tolerance=cfg.early_stopping_tolerance),
                         base_iteration=sum(s.iterations for s in cfg.stages[:stage_index]))
        resume, self._resume_in_stage = getattr(self, "_resume_in_stage", None), None
        if resume is not None and resume["stage"] == stage_index:  # a checkpoint written inside this stage
            resume_in_stage(self, work, resume)
        return work

    def _checkpoint_folder(self) -> Path | None:
        """The folder this process writes checkpoints to (None: none given, or a rank that does not write)."""
        directory = getattr(self, "_checkpoint_dir", None)
        return None if directory is None or (self.group is not None and not self.group.is_writer) else Path(directory)

    def _checkpoint_in_stage(self, work: StageWork) -> None:
        """A checkpoint inside the stage (``stage_<i>_it<k>.pt``, the older ones deleted) when a checkpoint folder is
        given and ``checkpoint_every_s`` of computation (not of the consumer's pauses) has passed since the last one."""
        if getattr(self, "_checkpoint_dir", None) is None:  # (the same on every rank: no collective needed)
            return
        directory, now = self._checkpoint_folder(), time.perf_counter()
        due = directory is not None and self.elapsed_s + (now - work.t0) - self._checkpointed_s >= self.config.checkpoint_every_s
        if self.group is not None and self.group.any(due):  # rank 0's clock decides; every row and its moments from its owner
            self._share_per_source_rows(optimiser_state=True)
        elif not due:
            return
        if directory is not None:
            path = write_checkpoint({**self.state_dict(), "in_stage": in_stage_state(work, now)},
                                    in_stage_path(directory, work.stage.index, work.done))
            prune_in_stage(directory, keep=path)
        self._checkpointed_s = self.elapsed_s + (time.perf_counter() - work.t0)

    def _end_stage(self, work: StageWork) -> Snapshot:
        """The stage's snapshot (the last complete state from now on) and its checkpoint."""
        snap = complete_stage(self, work.stage, work.record, work.base_iteration + work.stage.iterations, work.terms, work.t0,
                              work.validation_error, work.train_error)
        directory = self._checkpoint_folder()
        if directory is not None:
            self.save_checkpoint(checkpoint_path(directory, work.stage.index))
            prune_in_stage(directory)  # the stage's end holds what its checkpoints inside it held
            self._checkpointed_s = self.elapsed_s
        return snap

    # -- per-stage set-up -----------------------------------------------------------------------
    def _build_stage(self, stage_index: int) -> Stage:
        """Stage ``stage_index``'s model and images, its window planned for the current sources (every rank's alike)."""
        self._share_per_source_rows()
        sc = self.config.stages[stage_index]
        return build_stage(stage_index, sc.factor, sc.iterations, self.acquisition.optics, self.images,
                           self.calibration.sources_um(), device=self.device, coarse_model=self.coarse_model,
                           **self.stage_spec(stage_index).model_options())

    def stage_spec(self, stage_index: int, factor: int | None = None) -> StageSpec:
        """Stage ``stage_index``'s model with the parts as switched (:func:`~napari_fdt.recon.problem.stage_spec.stage_spec`;
        ``stage_index`` −1 with ``factor``: a stage off the schedule)."""
        return stage_spec(self.config, stage_index, self.coarse_model, {p for p, on in self.parts.items() if on}, self.camera, factor)

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

    def _set_step_size(self, vol_opt: torch.optim.Optimizer, stage: Stage, it: int) -> None:
        """The RI step of iteration ``it`` (1-based) of ``stage``: ``lr_ri``, in the finest stage decaying to
        ``lr_ri_final_ratio`` of it (:func:`napari_fdt.recon.settings.schedule.final_step_scale`)."""
        if stage.index == len(self.config.stages) - 1:
            for group in vol_opt.param_groups:
                group["lr"] = self.config.lr_ri * final_step_scale(it, stage.iterations, self.config.lr_ri_final_ratio)

    def _step(self, stage: Stage, mask: torch.Tensor | None, vol_opt: torch.optim.Optimizer, batch_size: int,
              data_range: float, progress: float, with_error: bool = False) -> tuple[dict[str, torch.Tensor], float | None]:
        """One iteration: next batch, prediction, loss, gradients (summed over ranks), one step of both optimisers.

        Returns the loss terms (tensors, unweighted; this rank's part of the data terms in a distributed run) and,
        with ``with_error`` (snapshots only: it waits for the device), the training images' relative error (None
        otherwise and for a rank with no training image in the batch).
        """
        # The batch's indices are split and ordered in host memory (numpy) and sent to the device once: on CUDA a decision read
        # from a device tensor (held.any(), a boolean index) would wait for the queue to drain at every iteration.
        idx_host = self.batches.next_host(batch_size)
        dn = self.volume.delta_n()
        share = None
        if self.group is not None:  # this rank's images of the batch, normalised by the whole batch
            idx = self.batches.to_device(idx_host)
            share = BatchShare.of_batch(None if mask is None else mask[idx], (len(idx), *stage.images.shape[1:]),
                                        regularisers=self.group.is_writer)
            idx_host = self.group.local(idx_host)
        held = self._held_out[idx_host] if len(self.validation_indices) else None
        # Either part may be empty (a batch of held-out images only, or a rank that owns none of the batch): an empty part
        # predicts nothing (spectral_images gives (0, h, w)), and the rank still joins the gradient sum below.
        if held is not None and bool(held.any()):  # held-out images last, through a constant volume and shared calibration
            n_train = int((~held).sum())
            idx = self.batches.to_device(np.concatenate([idx_host[~held], idx_host[held]]))
            pred = torch.cat([self._predict_normalised(stage, dn, idx[:n_train]),
                              self._predict_normalised(stage, dn, idx[n_train:], held_out=True)])
        else:
            idx = self.batches.to_device(idx_host)
            n_train = len(idx)
            pred = self._predict_normalised(stage, dn, idx)
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

    # -- validation (:mod:`napari_fdt.recon.loop.run_validation`) ----------------------------------------
    def validation_error(self, stage: Stage, mask: torch.Tensor | None = None) -> float | None:
        """Relative RMS error of the held-out images at ``stage`` (None without a validation split):
        :func:`napari_fdt.recon.loop.run_validation.validation_error`."""
        return validation_error(self, stage, mask)

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
        state = self.last_complete_state
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

    # -- checkpoints ----------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """The checkpoint's content (:func:`napari_fdt.recon.loop.checkpoint.checkpoint_state`)."""
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
        rec._make_plan()
        return rec

def reconstruct(acquisition: Acquisition, config: SolverConfig | None = None, *, device: str = "auto", **kwargs) -> Iterator[Snapshot]:
    """Shortcut: ``Reconstructor(acquisition, config, device=device).run(**kwargs)``."""
    return Reconstructor(acquisition, config, device=device).run(**kwargs)
