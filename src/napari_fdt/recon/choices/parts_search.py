"""The choice of the "auto" optional model parts in a run: each part tried on the held-out images, the pupil and
aberration parameters fitted to a subset of the training images through a cached exit field, and the choice recorded
(the rule, the parts and their constants are :mod:`napari_fdt.recon.loop.model_parts`'s; the switches
:mod:`napari_fdt.recon.choices.parts_switch`'s).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

import numpy as np
import torch

from napari_fdt.model.gain import least_squares_gain
from napari_fdt.model.render import iter_batches
from napari_fdt.physics.aberrations import ZERNIKE_MODES
from napari_fdt.recon.calibration.adam import Adam
from napari_fdt.recon.choices.parts_branch import branch_due, branch_trial, defers_the_rest
from napari_fdt.recon.choices.parts_switch import parts_chosen_by, set_parts
from napari_fdt.recon.loop.model_parts import (
    BINARY_PARTS,
    FIT_IMAGES,
    FIT_ITERATIONS,
    FIT_RATES,
    FITTED_PARTS,
    GRID_TRIAL_TRAINING_IMAGES,
    MIN_IMPROVEMENT,
    PartsChoice,
    decide,
    grid_waits_for_spectral,
    next_pass,
)
from napari_fdt.recon.loop.run_validation import image_errors, validation
from napari_fdt.recon.problem.stages import Stage

if TYPE_CHECKING:
    from napari_fdt.recon.loop.interface import Run

__all__ = ["choose_parts", "try_fitted_parts", "choice_errors", "trial_positions", "GRID_TRIAL_TRAINING_IMAGES", "fit_images",
           "pupil_values", "exit_cache", "fit_pupil_parts", "ExitCache"]


@dataclass
class ExitCache:
    """What :func:`exit_cache` computes once for the pupil fits: ``base``, the calibration's optics overrides other than
    the pupil's (NA, edge, Zernike coefficients), and ``chunks``, for chunks of the fit images (indices (B,),
    [(wavelength µm or None, weight, exit spectra, source spectra)])."""

    base: dict[str, Any]
    chunks: list[tuple[torch.Tensor, list[tuple[float | None, float, torch.Tensor, torch.Tensor]]]]


def choose_parts(rec: Run, stage: Stage, mask: torch.Tensor | None, should_stop: Callable[[], bool] | None) -> Stage | None:
    """Choose the "auto" parts at the start of ``stage`` (:mod:`napari_fdt.recon.loop.model_parts`) and return the stage
    as rebuilt for them; None when stopped meanwhile (the parts are then back to off)."""
    t0 = time.perf_counter()
    cal = rec.calibration
    provisional = dict(rec.parts)
    start_values = cal.copy_values()
    ref_err, ref_each = choice_errors(rec, stage, mask)
    reference = (ref_err, list(ref_each))
    trials: list[dict[str, Any]] = []

    def cancel() -> None:
        cal.restore_values(start_values)
        set_parts(rec, provisional)

    def trial(part: str) -> str | None:
        """Try ``part`` through the volume (and by a branch where that rejects a part of the finest model); the
        outcome: "on", "off", "deferred" (kept by a branch, the parts after it wait for the pass run again with it) or
        None when stopped."""
        nonlocal stage, mask, ref_each
        t1 = time.perf_counter()
        set_parts(rec, {**rec.parts, part: True})
        variant = stage if part == "spectral" else rec._build_stage(stage.index)
        vmask = rec._loss_mask(variant)
        cap = GRID_TRIAL_TRAINING_IMAGES if part == "field_grid" else None
        err, each = choice_errors(rec, variant, vmask, max_training=cap)
        verdict = decide(np.asarray(ref_each)[trial_positions(rec, cap)], each)
        trials.append({"part": part, "validation_error": err, "image_errors": each, **verdict,
                       "seconds": time.perf_counter() - t1})
        if not verdict["on"] and branch_due(rec, part):  # blind through this volume: a short branch of training with it
            set_parts(rec, {**rec.parts, part: False})
            branch = branch_trial(rec, stage, mask, part, should_stop)
            if branch is None:
                return None
            trials.append(branch)
            if branch["on"]:
                set_parts(rec, {**rec.parts, part: True})
                if defers_the_rest(rec):  # the other parts: at the end of the pass run again with it (physics first)
                    stage, mask = variant, vmask
                    return "deferred"
                verdict = {"on": True}
        if not verdict["on"]:
            set_parts(rec, {**rec.parts, part: False})
            return "off"
        if cap is not None:  # the next parts' reference: every test image
            err, each = choice_errors(rec, variant, vmask)
        stage, mask, ref_each = variant, vmask, each
        return "on"

    def grid_before_spectral(before: tuple[torch.Tensor | None, list[float]]) -> str | None:
        """The spectral model just passed its trial under ``field_oversampling = "before_spectral"``. Its blur can absorb
        what a field grid too coarse for the scattered light aliases (beads made on the 2x grid kept it in the grid's
        place; docs/decisions/parts-backward.md), so the grid, the physics, is tried first, from the reference before
        the spectral model (``before``: the loss mask and the per-image errors). The grid rejected: the spectral model
        is kept as tried. The grid kept: the spectral model's trial is set aside (``"waits_for"``) and, unless the parts
        wait for a pass run again with the grid, tried again through the grid's model. The outcome as :func:`trial`'s."""
        nonlocal mask, ref_each
        spectral, kept = trials[-1], (mask, ref_each)
        set_parts(rec, {**rec.parts, "spectral": False})
        mask, ref_each = before
        start = len(trials)
        grid = trial("field_grid")
        for t in trials[start:]:
            t["before_part"] = "spectral"
        if grid == "off":  # the spectral model as tried
            set_parts(rec, {**rec.parts, "spectral": True})
            mask, ref_each = kept
            return "on"
        if grid is not None:
            spectral.update(on=False, waits_for="field_grid")
        return trial("spectral") if grid == "on" else grid

    # the 2x grid under "before_spectral": tried only where the spectral model would be kept, and before it is
    grid_first = grid_waits_for_spectral(rec.config, rec._auto_parts)
    outcome: str | None = "off"
    for part in [p for p in BINARY_PARTS if p in rec._auto_parts and not (p == "field_grid" and grid_first)]:
        if rec._stop_requested(should_stop):
            cancel()
            return None
        before = (mask, ref_each)
        outcome = trial(part)
        if outcome == "on" and part == "spectral" and grid_first:
            outcome = grid_before_spectral(before)
        if outcome is None:
            cancel()
            return None
        if outcome == "deferred":
            break
    deferred = outcome == "deferred"
    fitted_auto = [p for p in FITTED_PARTS if p in rec._auto_parts and not deferred]
    if fitted_auto:
        tested = try_fitted_parts(rec, stage, mask, ref_each, fitted_auto, should_stop)
        if tested is None:
            cancel()
            return None
        trials += tested[0]
        ref_each = tested[1]
    choice = PartsChoice(dict(rec.parts), parts_chosen_by(rec), stage=stage.index, reference_error=reference[0],
                         reference_image_errors=reference[1], trials=trials,
                         fitted=pupil_values(rec, [p for p in FITTED_PARTS if rec.parts[p]]),
                         seconds=time.perf_counter() - t0)
    first = rec.parts_choice
    early = rec.early_trials
    if first is None and early is not None:  # the tests before this stage (the pilot, the coarse stage's end) kept nothing: theirs first
        choice.trials = early.trials + trials
        choice.seconds += early.seconds
    if first is not None and first.rerun in ("stages", "finest", "before"):
        # a later pass's choice (after every stage, or the finest stage, ran again with the kept parts; or after the
        # pilot kept parts before the stages): every pass's trials, each with its pass and what ran again before it,
        # and the first pass's reference (the pilot's, at Δn = 0, is not this choice's)
        n = next_pass(first.trials)
        choice.trials = first.trials + [{**t, "pass": n, "after": first.rerun} for t in trials]
        if first.rerun != "before":  # the first choice's reference, where it was made (the finest or a coarse stage's end)
            choice.reference_error, choice.reference_image_errors = first.reference_error, first.reference_image_errors
            choice.stage = first.stage
        choice.seconds += first.seconds
        choice.rerun = first.rerun
        rec._choose_again = []
    rec.apply_parts_choice(choice)
    return stage


def try_fitted_parts(rec: Run, stage: Stage, mask: torch.Tensor | None, ref_each: list[float], parts: list[str],
                     should_stop: Callable[[], bool] | None, min_improvement: float = MIN_IMPROVEMENT,
                     ) -> tuple[list[dict[str, Any]], list[float]] | None:
    """The paired test of the parts with parameters (``parts``: "pupil", "aberrations") through ``stage``'s model and the
    current volume: each fitted to :func:`fit_images` (:func:`fit_pupil_parts`) on top of the parts on, tested against
    the per-image errors ``ref_each`` (:func:`choice_errors`' images) and switched on (:func:`set_parts`) where kept, its
    fitted values kept in the calibration (set back where not); two kept parts are refitted together. Returns (the
    trials, the per-image errors with the kept parts), None when stopped (the caller sets the parts back).
    ``min_improvement``: :func:`~napari_fdt.recon.loop.model_parts.decide`'s floor."""
    cal, trials = rec.calibration, []
    t1 = time.perf_counter()
    cache = exit_cache(rec, stage)
    cache_s = time.perf_counter() - t1
    kept: list[str] = []
    for part in parts:
        t1 = time.perf_counter()
        before = cal.copy_values()
        if not fit_pupil_parts(rec, stage, cache, [part], should_stop):
            return None
        set_parts(rec, {**rec.parts, part: True})
        err, each = choice_errors(rec, stage, mask)
        verdict = decide(ref_each, each, min_improvement=min_improvement)
        trials.append({"part": part, "validation_error": err, "image_errors": each, **verdict,
                       "fitted": pupil_values(rec, [part]), "seconds": time.perf_counter() - t1 + cache_s})
        cache_s = 0.0
        if verdict["on"]:
            kept.append(part)
            ref_each = each
        else:
            set_parts(rec, {**rec.parts, part: False})
            cal.restore_values(before)
    if len(kept) > 1:  # refit together from the separate fits; kept if the held-out images agree
        t1 = time.perf_counter()
        before = cal.copy_values()
        if not fit_pupil_parts(rec, stage, cache, kept, should_stop):
            return None
        err, each = choice_errors(rec, stage, mask)
        joint = float(np.mean(each)) <= float(np.mean(ref_each))
        trials.append({"part": "+".join(kept), "validation_error": err, "image_errors": each, "on": joint,
                       "fitted": pupil_values(rec, kept), "seconds": time.perf_counter() - t1})
        if joint:
            ref_each = each
        else:
            cal.restore_values(before)
    return trials, ref_each


def _test_training_images(rec: Run) -> np.ndarray:
    """The training images the parts' test predicts: those the pupil parts are not fitted to."""
    return np.setdiff1d(np.setdiff1d(np.arange(rec.acquisition.n_images), rec.validation_indices), fit_images(rec).cpu().numpy())


def _subset(n: int, cap: int | None) -> np.ndarray:
    """Positions of at most ``cap`` of ``n`` items, evenly spread (all of them for None)."""
    if cap is None or n <= cap:
        return np.arange(n)
    return np.unique(np.round(np.linspace(0, n - 1, cap)).astype(int))


def trial_positions(rec: Run, max_training: int | None) -> np.ndarray:
    """Positions in :func:`choice_errors`' per-image list of the images a trial with ``max_training`` predicts."""
    n_held = len(rec.validation_indices)
    if rec.config.parts_test_images != "held_out+training":
        return np.arange(n_held)
    return np.concatenate([np.arange(n_held), n_held + _subset(len(_test_training_images(rec)), max_training)])


def choice_errors(rec: Run, stage: Stage, mask: torch.Tensor | None,
                  max_training: int | None = None) -> tuple[float, list[float]]:
    """(validation error, per-image errors the parts' paired test compares): the held-out images', and with
    ``parts_test_images`` ``"held_out+training"`` also those of the training images the parts' parameters are not
    fitted to (more images, a stronger test; biased against a part, since the volume and their positions were
    trained without it), at most ``max_training`` of them (evenly spread; :func:`trial_positions`)."""
    err, each = validation(rec, stage, mask, per_image=True)
    if rec.config.parts_test_images != "held_out+training":
        return err, each
    train = _test_training_images(rec)
    train = train[_subset(len(train), max_training)]
    more = image_errors(rec, stage, train, mask)[1]
    return err, list(each) + list(more)


def pupil_values(rec: Run, parts: list[str]) -> dict[str, Any]:
    """The calibration's current pupil values of ``parts``: NA and edge, Zernike coefficients by mode (rad)."""
    cal, out = rec.calibration, {}
    if "pupil" in parts:
        out["na"] = rec.acquisition.optics.na * float(cal.na_scale.detach())
        out["pupil_edge"] = abs(float(cal.pupil_edge.detach()))
    if "aberrations" in parts:
        out["zernike_rad"] = dict(zip(ZERNIKE_MODES, (float(v) for v in cal.zernike.detach().cpu())))
    return out


def fit_images(rec: Run) -> torch.Tensor:
    """Up to :data:`FIT_IMAGES` training images, evenly spread over them (the subset the pupil parts are fitted to)."""
    train = np.setdiff1d(np.arange(rec.acquisition.n_images), rec.validation_indices)
    pick_ = np.unique(np.round(np.linspace(0, len(train) - 1, min(FIT_IMAGES, len(train)))).astype(int))
    return torch.as_tensor(train[pick_], device=rec.device)


def exit_cache(rec: Run, stage: Stage) -> ExitCache:
    """For chunks of the fit images: (indices, [(wavelength, weight, exit spectra, source spectra)]) through the current
    volume and sources (:meth:`MultiSliceModel.exit_spectra`), computed once for every pupil tried."""
    cal, model = rec.calibration, stage.model
    base = {k: v for k, v in cal.optics_overrides(stage.optics, False, shared_frozen=True).items()
            if k not in ("na", "pupil_edge", "zernike")}
    lams = list(zip(rec.wavelengths, rec.weights)) if rec.wavelengths else [(None, 1.0)]
    out = []
    with torch.no_grad():
        dn = stage.to_field_grid(rec.volume.delta_n())
        idx_all = fit_images(rec) if rec.group is None else rec.group.local(fit_images(rec))  # (a rank's own: their rows)
        for sl in iter_batches(len(idx_all), rec.config.batch_size):
            idx = idx_all[sl]
            src = stage.stage_sources(cal.calibrated_sources()[idx])
            per = []
            for lam, w in lams:
                k = model.kernels(**base, wavelength_um=lam) if (base or lam is not None) else None
                per.append((lam, w, *model.exit_spectra(dn, src, k)))
            out.append((idx, per))
    return ExitCache(base, out)


def fit_pupil_parts(rec: Run, stage: Stage, cache: ExitCache, parts: list[str], should_stop: Callable[[], bool] | None) -> bool:
    """Fit the parameters of ``parts`` ("pupil", "aberrations") to the fit images with the volume and sources fixed:
    :data:`FIT_ITERATIONS` Adam steps on the sum of the images' squared relative errors (gains in closed form),
    from the calibration's current values, which are set to the result. False when stopped. In a distributed run each
    rank's ``cache`` holds its own fit images and the gradients are summed over ranks (every rank steps alike)."""
    cal, model, base = rec.calibration, stage.model, cache.base
    na = cal.na_scale.detach().clone().requires_grad_("pupil" in parts)
    edge = cal.pupil_edge.detach().clone().requires_grad_("pupil" in parts)
    zern = cal.zernike.detach().clone().requires_grad_("aberrations" in parts)
    groups = []
    if "pupil" in parts:
        groups += [{"params": [na], "lr": FIT_RATES["na_scale"]}, {"params": [edge], "lr": FIT_RATES["pupil_edge"]}]
    if "aberrations" in parts:
        groups.append({"params": [zern], "lr": FIT_RATES["zernike"]})
    opt = Adam(groups, betas=(0.9, 0.99))
    on_pupil = "pupil" in parts or rec.parts["pupil"]
    on_aber = "aberrations" in parts or rec.parts["aberrations"]
    for _ in range(FIT_ITERATIONS):
        if rec._stop_requested(should_stop):
            return False
        opt.zero_grad(set_to_none=True)
        for idx, per in cache.chunks:
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
        if rec.group is not None:  # the ranks' chunks add up to every fit image's (a rank with none adds zeros)
            rec.group.reduce_gradients([na, edge, zern], [])
        opt.step()
    with torch.no_grad():
        cal.na_scale.copy_(na)
        cal.pupil_edge.copy_(edge)
        cal.zernike.copy_(zern)
    return True
