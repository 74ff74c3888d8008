"""The reconstruction: one solver loop, exposed as a generator of snapshots.

``Reconstructor(acquisition, config).run()`` yields a :class:`Snapshot` every ``snapshot_every``
iterations and at the end of every stage (``stage_complete=True``). Stopping the iteration (or calling
``close()`` on the generator) cancels between iterations; :attr:`Reconstructor.last_complete` then holds
the last complete stage. The command line, the napari widgets and the benchmarks all drive this loop.

What is optimised (``docs/solver.md``): the explicit RI grid (:class:`~napari_fdt.recon.volume.RIVolume`), a
log-gain per image, and (from ``calibration_from_stage``) the lateral position of every source, a common
offset of the source plane's depth, and optionally the pixel size and slice spacing as global scales.
The RI grid has its own Adam optimiser, rebuilt at each stage (its moments belong to voxels that the
resampling replaces); the calibration parameters keep one Adam optimiser for the whole run.

Given a :class:`~napari_fdt.recon.distributed.Group` (``group=``), the run is one rank of a data-parallel
reconstruction (``docs/distributed.md``): each rank computes the images it owns of every batch, the
gradients of the shared parameters are summed over ranks, and the result equals the single-process one.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator

import numpy as np
import torch

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.device import resolve_device
from napari_fdt.errors import FDTInputError
from napari_fdt.model.coherence import coherence_masks, emission_spectrum, spectral_images
from napari_fdt.physics.grid import plan_for_sources
from napari_fdt.recon.config import SolverConfig, resolve_coarse_model
from napari_fdt.recon.losses import BatchShare, LossWeights, as_floats, total_loss
from napari_fdt.recon.stages import Stage, build_stage
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
    iteration (unweighted); times in seconds.
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

    @property
    def seconds_per_iteration(self) -> float:
        return self.seconds / self.iterations if self.iterations else 0.0

    def to_dict(self) -> dict[str, Any]:
        return {"stage": self.stage, "factor": self.factor, "field_factor": self.field_factor, "grid": list(self.grid), "window": list(self.window),
                "na": self.na, "model": self.model, "iterations": self.iterations, "seconds": self.seconds,
                "seconds_per_iteration": self.seconds_per_iteration}


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
        self.config = config or SolverConfig()
        self.device = resolve_device(device)
        self.dtype = torch.float32
        cfg = self.config
        #: the coarse stages' model after resolving "auto" for this device
        self.coarse_model = resolve_coarse_model(cfg.coarse_model, self.device.type)
        o = acquisition.optics
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
        self.image_scale = mean
        _warn_about_images(acquisition)
        plan_for_sources(o, acquisition.image_shape, src)  # FDTWarning for sampling problems, before any run
        self.images = torch.from_numpy(imgs / mean)
        self.full_shape = acquisition.image_shape
        dev, dt = self.device, self.dtype
        self.sources = torch.tensor(src, device=dev, dtype=dt)
        self.log_gain = torch.zeros(n_img, device=dev, dtype=dt)
        self.pixel_scale = torch.ones((), device=dev, dtype=dt)
        self.spacing_scale = torch.ones((), device=dev, dtype=dt)
        self.depth_offset_um = torch.zeros((), device=dev, dtype=dt)
        self._gain_initialised = False
        self.volume: RIVolume | None = None
        self.volume_factor: int | None = None
        self._cal_opt: torch.optim.Adam | None = None
        self._batch_gen = torch.Generator().manual_seed(cfg.seed)
        self._order: list[int] = []
        self.completed_stages = 0
        self.stages: list[StageRecord] = []
        self.history: list[dict[str, Any]] = []
        self.elapsed_s = 0.0
        self.last_complete: Snapshot | None = None
        self.final_losses: dict[str, float] = {}
        if cfg.coherence in ("spectral", "mask+spectral"):
            lams, ws = emission_spectrum(o.wavelength_um, cfg.bandwidth_um, cfg.n_wavelengths)
            self.wavelengths, self.weights = list(map(float, lams)), list(map(float, ws))
        else:
            self.wavelengths, self.weights = None, None
        self.loss_weights = LossWeights.from_config(cfg)
        self._check_memory(src)

    def _check_memory(self, sources_um: np.ndarray) -> None:
        """Refuse, before any allocation, a batch whose finest multi-slice stage would not fit in memory."""
        from napari_fdt.device import available_bytes
        from napari_fdt.model.memory import grid_is_unitary, leanest_mode, training_bytes
        from napari_fdt.recon.stages import multislice_plan

        cfg = self.config
        o = self.acquisition.optics
        free = available_bytes(self.device)
        if free is None:
            return
        finest_index = min(range(len(cfg.stages)), key=lambda i: cfg.stages[i].factor)
        _, opt, _, plan = multislice_plan(o, cfg.stages[finest_index].factor, self.full_shape, sources_um)
        k = len(self.wavelengths) if self.wavelengths else 1
        batch = min(cfg.stage_batch(finest_index), self.acquisition.n_images)
        mode = cfg.backward_mode
        if mode == "auto":  # auto falls back to the leanest mode when one field per slice does not fit
            mode = leanest_mode(grid_is_unitary(opt.pixel_size_um, o.n_background, o.wavelength_um))
        # the finest stage's images live on the device too (float32, all of them)
        images = 4 * self.acquisition.n_images * self.full_shape[0] * self.full_shape[1]
        need = training_bytes(plan.padded_shape, o.n_slices, batch, k, mode) + images
        if need <= 0.9 * free:
            return
        fits = int((0.9 * free - images) // max(1, training_bytes(plan.padded_shape, o.n_slices, 1, k, mode)))
        gib = 2.0**30
        fix = (f"lower batch_size to {fits}" if fits >= 1 else
               "crop the images, use fewer slices or fewer wavelengths, or a device with more memory")
        raise FDTInputError(
            "batch_size",
            f"a batch of {batch} images needs about {need / gib:.1f} GiB on {self.device} "
            f"({plan.padded_shape[0]}x{plan.padded_shape[1]} window, {o.n_slices} slices, {k} wavelength(s), "
            f"backward mode {mode}); "
            f"{free / gib:.1f} GiB are free",
            fix,
        )

    # -- parameters ---------------------------------------------------------------------------
    def calibrated_sources(self) -> torch.Tensor:
        """(N, 3) positions with the common depth offset applied (acquisition coordinates)."""
        offset = torch.stack([torch.zeros_like(self.depth_offset_um), torch.zeros_like(self.depth_offset_um), self.depth_offset_um])
        return self.sources + offset

    def calibration(self) -> dict[str, float]:
        o = self.acquisition.optics
        return {
            "pixel_size_um": o.pixel_size_um * float(self.pixel_scale.detach()),
            "slice_spacing_um": o.slice_spacing_um * float(self.spacing_scale.detach()),
            "source_depth_offset_um": float(self.depth_offset_um.detach()),
        }

    def _overrides(self, stage: Stage) -> dict[str, torch.Tensor]:
        cfg = self.config
        out = {}
        if cfg.calibrate_pixel_size and not stage.envelope:
            out["pixel_size_um"] = stage.optics.pixel_size_um * self.pixel_scale
        if cfg.calibrate_slice_spacing:
            out["slice_spacing_um"] = stage.optics.slice_spacing_um * self.spacing_scale
        return out

    def _set_trainable(self, stage_index: int) -> None:
        cfg = self.config
        on = stage_index >= cfg.calibration_from_stage
        self.sources.requires_grad_(on and cfg.calibrate_sources)
        self.depth_offset_um.requires_grad_(on and cfg.calibrate_source_depth)
        self.pixel_scale.requires_grad_(on and cfg.calibrate_pixel_size)
        self.spacing_scale.requires_grad_(on and cfg.calibrate_slice_spacing)
        self.log_gain.requires_grad_(cfg.calibrate_gain)
        if self._cal_opt is None:
            cfg = self.config
            self._cal_opt = torch.optim.Adam(
                [
                    {"params": [self.sources], "lr": cfg.lr_sources_um},
                    {"params": [self.log_gain], "lr": cfg.lr_log_gain},
                    {"params": [self.pixel_scale, self.spacing_scale], "lr": cfg.lr_global},
                    {"params": [self.depth_offset_um], "lr": cfg.lr_sources_um},
                ],
                betas=(0.9, 0.99),
            )

    def _next_batch(self, batch_size: int) -> torch.Tensor:
        n = self.acquisition.n_images
        b = min(batch_size, n)
        while len(self._order) < b:
            self._order.extend(torch.randperm(n, generator=self._batch_gen).tolist())
        idx, self._order = self._order[:b], self._order[b:]
        t = torch.tensor(idx)
        if self.device.type == "cuda":  # pinned + non-blocking: no wait for the GPU's queue to drain
            return t.pin_memory().to(self.device, non_blocking=True)
        return t.to(self.device)

    def _predict(self, stage: Stage, dn: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        src = stage.stage_sources(self.calibrated_sources()[idx])
        # Only the lateral position of each source is calibrated; depth moves through the common offset.
        gain = torch.exp(self.log_gain[idx])
        return spectral_images(stage.model, stage.to_field_grid(dn), src, gain, self.wavelengths, self.weights,
                               **self._overrides(stage))

    def _init_gains(self, stage: Stage, mask: torch.Tensor | None) -> None:
        """Least-squares gain per image against the homogeneous-medium prediction."""
        n = self.acquisition.n_images
        zero = torch.zeros((self.acquisition.optics.n_slices, *stage.image_shape), device=self.device, dtype=self.dtype)  # field grid
        gains = torch.empty(n, device=self.device, dtype=self.dtype)
        with torch.no_grad():
            for start in range(0, n, self.config.batch_size):
                idx = torch.arange(start, min(n, start + self.config.batch_size), device=self.device)
                src = stage.stage_sources(self.calibrated_sources()[idx])
                pred = spectral_images(stage.model, zero, src, None, self.wavelengths, self.weights)
                meas = stage.images[idx]
                m = torch.ones_like(meas) if mask is None else mask[idx]
                num = (pred * meas * m).sum(dim=(-2, -1))
                den = (pred * pred * m).sum(dim=(-2, -1)).clamp_min(1e-30)
                gains[idx] = (num / den).clamp_min(1e-6)
            self.log_gain.copy_(torch.log(gains))
        self._gain_initialised = True

    # -- the loop -----------------------------------------------------------------------------
    def _stage_cost(self, factor: int) -> float:
        """Rough relative cost of an iteration at a stage factor (grid area the model works on)."""
        from napari_fdt.recon.stages import field_factor

        g = factor if (factor > 1 and self.coarse_model == "envelope") else field_factor(self.acquisition.optics, factor)
        h, w = self.full_shape
        return (h / g) * (w / g)

    def _snapshot(self, stage: Stage, it: int, global_it: int, terms: dict, stage_t0: float, complete: bool) -> Snapshot:
        cfg = self.config
        terms = self._gather(terms, optimiser_state=complete)
        now = time.perf_counter()
        elapsed = self.elapsed_s + (now - stage_t0)
        per_it = (now - stage_t0) / max(it, 1)
        remaining = (stage.iterations - it) * per_it
        cur_cost = self._stage_cost(stage.factor)
        for s in cfg.stages[stage.index + 1 :]:
            remaining += s.iterations * per_it * self._stage_cost(s.factor) / cur_cost
        losses = as_floats(terms) if terms else {}
        snap = Snapshot(
            stage=stage.index, n_stages=len(cfg.stages), factor=stage.factor, iteration=it,
            stage_iterations=stage.iterations, global_iteration=global_it, total_iterations=cfg.total_iterations,
            delta_n=self.volume.delta_n().detach().cpu().numpy().astype(np.float32),
            sources_um=self.calibrated_sources().detach().cpu().double().numpy(),
            gains=(torch.exp(self.log_gain).detach().cpu().double().numpy() * self.image_scale),
            calibration=self.calibration(), losses=losses, elapsed_s=elapsed, eta_s=remaining,
            stage_complete=complete, full_shape=self.full_shape,
        )
        self.history.append({"stage": stage.index, "iteration": it, "global_iteration": global_it,
                             "elapsed_s": elapsed, **losses})
        return snap

    def run(self, should_stop: Callable[[], bool] | None = None, checkpoint_dir: str | Path | None = None) -> Iterator[Snapshot]:
        """Run the remaining stages, yielding snapshots. ``should_stop()`` is polled between iterations."""
        cfg = self.config
        o = self.acquisition.optics
        torch.manual_seed(cfg.seed + self.completed_stages)
        global_it = sum(s.iterations for s in cfg.stages[: self.completed_stages])
        self._share_per_source_rows()
        for si in range(self.completed_stages, len(cfg.stages)):
            sc = cfg.stages[si]
            stage = build_stage(si, sc.factor, sc.iterations, o, self.images,
                                self.calibrated_sources().detach().cpu().double().numpy(), device=self.device,
                                coarse_model=self.coarse_model, backward_mode=cfg.backward_mode,
                                obliquity="per_source" if cfg.obliquity_correction else "none")
            h, w = stage.grid_shape
            if self.volume is None:
                self.volume = RIVolume((o.n_slices, h, w), delta_n_max=cfg.delta_n_max, activation=cfg.activation,
                                       device=self.device, dtype=self.dtype)
            elif self.volume_factor != sc.factor:
                self.volume.resample(self.volume_factor, sc.factor, self.full_shape)
            self.volume_factor = sc.factor
            mask = stage.coverage
            if cfg.coherence in ("mask", "mask+spectral"):
                cm = coherence_masks(stage.model, stage.stage_sources(self.calibrated_sources().detach()),
                                     threshold=cfg.mask_threshold, wavelengths_um=self.wavelengths, weights=self.weights)
                mask = cm if mask is None else mask * cm
            if not self._gain_initialised:
                self._init_gains(stage, mask)
            self._set_trainable(si)
            vol_opt = torch.optim.Adam([self.volume.x], lr=cfg.lr_ri, betas=(0.9, 0.99))
            stage_batch = cfg.stage_batch(si)
            data_range = float(stage.images.max())
            record = StageRecord(si, sc.factor, stage.field_factor, (o.n_slices, h, w), stage.window, stage.optics.na,
                                 sc.iterations, model="envelope" if stage.envelope else "multislice")
            self.stages = [r for r in self.stages if r.stage != si] + [record]
            t0 = time.perf_counter()
            terms: dict = {}
            for it in range(1, sc.iterations + 1):
                if should_stop is not None and (self.group.any(should_stop()) if self.group else should_stop()):
                    self.elapsed_s += time.perf_counter() - t0
                    return
                idx = self._next_batch(stage_batch)
                dn = self.volume.delta_n()
                share = None
                if self.group is not None:  # this rank's images of the batch, normalised by the whole batch
                    share = BatchShare.of_batch(None if mask is None else mask[idx], (len(idx), *stage.images.shape[1:]),
                                                regularisers=self.group.is_writer)
                    idx = self.group.local(idx)
                # A rank with no image in this batch predicts none (and still joins the gradient sum).
                pred = self._predict(stage, dn, idx) if len(idx) else stage.images[idx]
                m = None if mask is None else mask[idx]
                progress = global_it / max(1, cfg.total_iterations)
                loss, terms = total_loss(pred, stage.images[idx], dn, self.loss_weights, progress, mask=m,
                                         data_range=data_range, share=share)
                vol_opt.zero_grad(set_to_none=True)
                self._cal_opt.zero_grad(set_to_none=True)
                if loss.requires_grad:
                    loss.backward()
                if self.group is not None:
                    self.group.reduce_gradients([self.volume.x, self.pixel_scale, self.spacing_scale, self.depth_offset_um],
                                                [self.sources, self.log_gain])
                vol_opt.step()
                self._cal_opt.step()
                global_it += 1
                if it == sc.iterations:
                    break
                if it % cfg.snapshot_every == 0:
                    snap = self._snapshot(stage, it, global_it, terms, t0, False)
                    paused = time.perf_counter()
                    yield snap
                    t0 += time.perf_counter() - paused  # time spent by the consumer is not the solver's
            record.seconds = time.perf_counter() - t0
            snap = self._snapshot(stage, sc.iterations, global_it, terms, t0, True)
            self.elapsed_s += record.seconds
            snap.elapsed_s = self.elapsed_s
            self.completed_stages = si + 1
            self.last_complete = snap
            self._last_complete_state = self._capture()
            self.final_losses = snap.losses
            if checkpoint_dir is not None and (self.group is None or self.group.is_writer):
                self.save_checkpoint(Path(checkpoint_dir) / f"stage_{si}.pt")
            yield snap

    def _share_per_source_rows(self, optimiser_state: bool = False) -> None:
        """Distributed: every rank gets each image's source and gain rows (and their Adam moments) from its owner."""
        if self.group is None:
            return
        tensors = [self.sources, self.log_gain]
        if optimiser_state and self._cal_opt is not None:
            for p in (self.sources, self.log_gain):
                state = self._cal_opt.state.get(p, {})
                tensors += [state.get("exp_avg"), state.get("exp_avg_sq")]
        self.group.share_rows(tensors)

    def _gather(self, terms: dict, optimiser_state: bool = False) -> dict:
        """Distributed: the whole batch's loss terms and every image's rows on every rank (a collective).

        The data terms and the total are sums of the ranks' parts; the regularisers are the same on all.
        """
        if self.group is None:
            return terms
        self._share_per_source_rows(optimiser_state)
        return self.group.sum_terms(terms, ("l1", "l2", "ssim_loss", "total")) if terms else terms

    def _capture(self) -> dict[str, Any]:
        """Copies of the optimised state (small tensors), to return to after a cancel."""
        return {
            "x": self.volume.x.detach().clone(), "factor": self.volume_factor,
            "sources": self.sources.detach().clone(), "log_gain": self.log_gain.detach().clone(),
            "pixel_scale": self.pixel_scale.detach().clone(), "spacing_scale": self.spacing_scale.detach().clone(),
            "depth_offset_um": self.depth_offset_um.detach().clone(), "elapsed_s": self.elapsed_s,
            "stages": list(self.stages),
        }

    def restore_last_complete(self) -> None:
        """Return to the state at the end of the last complete stage (after a cancel mid-stage)."""
        state = getattr(self, "_last_complete_state", None)
        if state is None:
            raise RuntimeError("no stage has completed yet")
        with torch.no_grad():
            self.volume.x = state["x"].clone().requires_grad_()
            self.volume_factor = state["factor"]
            for name in ("sources", "log_gain", "pixel_scale", "spacing_scale", "depth_offset_um"):
                getattr(self, name).copy_(state[name])
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

    # -- checkpoints ----------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {
            "format": "napari-fdt-checkpoint", "version": 1,
            "config": self.config.to_dict(), "completed_stages": self.completed_stages,
            "volume": None if self.volume is None else self.volume.state_dict(), "volume_factor": self.volume_factor,
            "sources": self.sources.detach().cpu(), "log_gain": self.log_gain.detach().cpu(),
            "pixel_scale": self.pixel_scale.detach().cpu(), "spacing_scale": self.spacing_scale.detach().cpu(),
            "depth_offset_um": self.depth_offset_um.detach().cpu(),
            "gain_initialised": self._gain_initialised,
            "cal_opt": None if self._cal_opt is None else self._cal_opt.state_dict(),
            "batch_gen": self._batch_gen.get_state(), "order": list(self._order),
            "stages": [r.to_dict() for r in self.stages], "history": self.history, "elapsed_s": self.elapsed_s,
            "initial_sources_um": self.initial_sources_um, "n_images": self.acquisition.n_images,
            "image_shape": list(self.full_shape),
        }

    def save_checkpoint(self, path: str | Path) -> Path:
        """Write the state atomically (temporary file, then rename)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp")
        torch.save(self.state_dict(), tmp)
        tmp.replace(path)
        return path

    @classmethod
    def from_checkpoint(cls, path: str | Path, acquisition: Acquisition, *, device: str | torch.device = "auto",
                        group: Group | None = None) -> "Reconstructor":
        """Resume: the next :meth:`run` continues with the first stage the checkpoint had not completed."""
        try:
            state = torch.load(Path(path), map_location="cpu", weights_only=False)
        except (OSError, RuntimeError, EOFError) as exc:
            raise FDTInputError("resume", f"cannot read checkpoint {path}: {exc}", "point --resume at a stage_*.pt file") from None
        if not isinstance(state, dict) or state.get("format") != "napari-fdt-checkpoint":
            raise FDTInputError("resume", f"{path} is not a napari-fdt checkpoint", "point --resume at a stage_*.pt file")
        if state["n_images"] != acquisition.n_images or tuple(state["image_shape"]) != acquisition.image_shape:
            raise FDTInputError("resume", "the checkpoint belongs to an acquisition of another size", "resume with the same acquisition")
        rec = cls(acquisition, SolverConfig.from_dict(state["config"]), device=device, initial_sources_um=state["initial_sources_um"],
                  group=group)
        with torch.no_grad():
            rec.sources.copy_(state["sources"])
            rec.log_gain.copy_(state["log_gain"])
            rec.pixel_scale.copy_(state["pixel_scale"])
            rec.spacing_scale.copy_(state["spacing_scale"])
            rec.depth_offset_um.copy_(state["depth_offset_um"])
        rec._gain_initialised = state["gain_initialised"]
        if state["volume"] is not None:
            rec.volume = RIVolume.from_state_dict(state["volume"], rec.device, rec.dtype)
        rec.volume_factor = state["volume_factor"]
        rec.completed_stages = state["completed_stages"]
        if state["cal_opt"] is not None:
            rec._set_trainable(max(0, rec.completed_stages - 1))
            rec._cal_opt.load_state_dict(state["cal_opt"])
        rec._batch_gen.set_state(state["batch_gen"])
        rec._order = list(state["order"])
        rec.stages = [StageRecord(r["stage"], r["factor"], r["field_factor"], tuple(r["grid"]), tuple(r["window"]), r["na"], r["iterations"], r["seconds"], r["model"])
                      for r in state["stages"]]
        rec.history = list(state["history"])
        rec.elapsed_s = float(state["elapsed_s"])
        return rec


def _warn_about_images(acquisition: Acquisition) -> None:
    """Warn (FDTWarning) about blank images and saturated pixels, which the intensity model cannot explain."""
    import warnings

    from napari_fdt.errors import FDTWarning

    imgs = acquisition.images
    n = imgs.shape[0]
    blank = np.flatnonzero(imgs.reshape(n, -1).max(axis=1) <= 0)
    if blank.size:
        listed = ", ".join(map(str, blank[:10])) + (" …" if blank.size > 10 else "")
        warnings.warn(f"images: {blank.size} of {n} images are blank (no positive pixel): {listed}; they carry no "
                      "information and their gain goes to about 0: drop them from the acquisition", FDTWarning, stacklevel=3)
    top = np.iinfo(imgs.dtype).max if imgs.dtype.kind == "u" else float(imgs.max())
    if top > 0:
        at_top = int(np.count_nonzero(imgs == top))
        if at_top > max(10, 1e-3 * imgs.size):
            warnings.warn(f"images: {at_top} pixels ({100 * at_top / imgs.size:.2f} %) sit at the maximum value {top:g}: "
                          "saturated pixels break the intensity model; mask them or re-acquire with less exposure",
                          FDTWarning, stacklevel=3)


def reconstruct(acquisition: Acquisition, config: SolverConfig | None = None, *, device: str = "auto", **kwargs) -> Iterator[Snapshot]:
    """Shortcut: ``Reconstructor(acquisition, config, device=device).run(**kwargs)``."""
    return Reconstructor(acquisition, config, device=device).run(**kwargs)
