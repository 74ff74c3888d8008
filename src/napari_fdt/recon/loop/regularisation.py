"""Automatic regularisation: the TV weights chosen from the data by the validation error.

With ``tv_xy_weight = "auto"`` (the default; ``tv_z_weight`` likewise) the weights are chosen inside the run
(:mod:`napari_fdt.recon.choices.tv_search`; the rule and its measured cost are in ``docs/solver.md``):

1. The stages before the *selection stage* (:func:`selection_stages`) run at the path's smallest weight (τ_xy 1: some
   TV is always wanted, below); at the selection stage's start, in increasing weight until one is worse than the best
   by more than the images' noise (:func:`tried_enough`), every candidate of :data:`TV_PATH` trains from the same
   state (volume, calibration and their optimisers, batch order: common random numbers, so that the candidates differ
   only by their weight) for :data:`PROBE_SHARE` of the stage's iterations, and ends with the validation error of each
   held-out image (:mod:`napari_fdt.recon.assess.validation`).
2. The weight of lowest validation error is the reference; a larger weight wins if it is not significantly worse
   than it, image by image (:func:`pick`): the mean over the held-out images of its error minus the reference's is at
   most one standard error of that mean (a paired one-standard-error rule: the candidates are compared on the same
   images from the same state, so their differences are measured far more precisely than each error). Of such
   volumes the smoother one is the one that has not filled with what the data cannot constrain; measured, the plain
   lowest error regularised less than the RI error wanted on beads, cells and deep sources, and the unpaired rule
   (the spread of each error over the images) more than it wanted on the sample and cells.
3. Where the winner is what the stages before ran with (the smallest weight), or there were none, the stage goes on from the
   winning trial's state (volume, calibration, both optimisers, batch order): only the losing trials' iterations are
   extra work. Otherwise the weight changes what the stages before did, and they run again with it from the start,
   the selection stage in full: an "auto" run always ends as the run given its chosen weights as numbers. (Keeping the
   first stage's state whatever the choice, TV-free or at τ 1, measurably raised the Δn error:
   docs/decisions/tv-weight-choice.md.)

τ_z follows τ_xy at the ratio :data:`TV_Z_RATIO` when both are ``"auto"``; a weight given as a number stays fixed
while the other is chosen. Without a validation split "auto" means the path's smallest weight, with a warning.

No TV (τ 0) is not a candidate: with a missing cone, an unregularised volume fills what no image constrains, and on
every scene of the suite a fixed τ_xy 1 ends below τ 0 on the mean over seeds (14 of 16 seed pairs;
docs/decisions/tv-weight-choice.md, "No TV is not a candidate"). The held-out images could not tell them apart (on the
sample 0.1612 against 0.1608), so the choice between them flipped with small changes of the coarse model and cost up
to 2.7× the Δn error. A weight given as a number, 0 included, is used as given.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from napari_fdt.recon.settings.config import AUTO, SolverConfig

__all__ = ["TV_PATH", "TV_Z_RATIO", "STANDARD_ERRORS", "PROBE_SHARE", "TVChoice", "tv_is_auto", "candidate_weights", "pick",
           "tried_enough", "selection_stages"]

#: Candidate lateral TV weights τ_xy, log-spaced over the range where the measured optimum of our scenes lies
#: (docs/ablation.md: from 1 on the bundled sample to about 50 on the authors' demo geometry); no TV is not one
#: (the module's docstring).
TV_PATH: tuple[float, ...] = (1.0, 3.0, 10.0, 30.0, 100.0)
#: τ_z / τ_xy when both are chosen (the issue's "TV 50/25").
TV_Z_RATIO = 0.5
#: Standard errors of the paired difference within which a larger weight still counts as not worse than the best.
STANDARD_ERRORS = 1.0
#: Share of the selection stage's iterations each candidate trains for.
PROBE_SHARE = 0.3


def tv_is_auto(config: SolverConfig) -> bool:
    """Whether any TV weight of ``config`` is chosen from the data."""
    return AUTO in (config.tv_xy_weight, config.tv_z_weight)


def candidate_weights(config: SolverConfig, tau_xy: float) -> tuple[float, float]:
    """(τ_xy, τ_z) of the candidate ``tau_xy``: "auto" fields take it (τ_z at :data:`TV_Z_RATIO`), numbers stay."""
    xy = tau_xy if config.tv_xy_weight == AUTO else float(config.tv_xy_weight)
    if config.tv_z_weight != AUTO:
        z = float(config.tv_z_weight)
    elif config.tv_xy_weight == AUTO:
        z = TV_Z_RATIO * tau_xy
    else:  # τ_xy fixed, τ_z chosen: the path runs over τ_z itself
        z = tau_xy
    return xy, z


def _as_good(trial: dict[str, Any], best: dict[str, Any], standard_errors: float) -> bool:
    """Whether ``trial`` is not significantly worse than ``best``: the mean of its per-image errors minus ``best``'s
    is at most ``standard_errors`` standard errors of that mean (with fewer than 2 images: its error is not larger)."""
    if trial is best:
        return True
    d = np.asarray(trial.get("image_errors", []), dtype=np.float64) - np.asarray(best.get("image_errors", []), dtype=np.float64)
    if d.size < 2:
        return trial["validation_error"] <= best["validation_error"]
    return bool(d.mean() <= standard_errors * d.std(ddof=1) / np.sqrt(d.size))


def pick(trials: list[dict[str, Any]], standard_errors: float = STANDARD_ERRORS) -> dict[str, Any]:
    """The winning trial. The reference is the lowest ``validation_error``; a trial with a larger weight (``tau``) is
    as good when the mean of its per-image errors (``image_errors``) minus the reference's, over the same images, is
    at most ``standard_errors`` standard errors of that mean. The largest such weight wins."""
    best = min(trials, key=lambda t: t["validation_error"])
    return max((t for t in trials if t["tau"] >= best["tau"] and _as_good(t, best, standard_errors)), key=lambda t: t["tau"])


def tried_enough(trials: list[dict[str, Any]], standard_errors: float | None = None) -> bool:
    """Whether the trials so far (in increasing weight) decide :func:`pick`: the last one has a larger weight than the
    lowest-error one and its mean paired rise over it, image by image, exceeds ``standard_errors`` standard errors of
    that mean (None: Student's t(0.975, n − 1) for n held-out images, the model parts' noise rule,
    :func:`~napari_fdt.recon.loop.model_parts.standard_errors`). The held-out error rises with the weight past its minimum,
    so a larger weight would not be picked either. A rise the images' own spread could make does not stop the path:
    with one standard error (the rule until 2026-11-27) a 0.2 % rise stopped an unseen sparse scene at τ 1 where going
    on picked τ 10 and an 18 % better volume; on 7 scenes × 3 seeds (the suite and a thick slab, ``benchmarks/tv_stop_rule.py``) the
    stricter stop picks the same weight every time, trying one weight more on 17 of 21
    (docs/decisions/tv-weight-choice.md). Without a noise
    estimate (fewer than 2 images) the path is never cut."""
    from napari_fdt.recon.loop.model_parts import standard_errors as t_quantile

    if len(trials) < 2:
        return False
    best = min(trials, key=lambda t: t["validation_error"])
    last = trials[-1]
    d = np.asarray(last.get("image_errors", []), dtype=np.float64) - np.asarray(best.get("image_errors", []), dtype=np.float64)
    if last["tau"] <= best["tau"] or d.size < 2:
        return False
    k = t_quantile(d.size) if standard_errors is None else standard_errors
    return bool(d.mean() > k * d.std(ddof=1) / np.sqrt(d.size))


def selection_stages(config: SolverConfig) -> list[int]:
    """Stages at which the weights are chosen: the last coarse stage (factor > 1), else the first stage."""
    coarse = [i for i, s in enumerate(config.stages) if s.factor > 1 and s.iterations > 0]
    return [coarse[-1]] if coarse else [0]


@dataclass
class TVChoice:
    """What the automatic choice tried and chose (RI.json's ``regularisation``)."""

    tv_xy_weight: float
    tv_z_weight: float
    stage: int
    probe_iterations: int
    trials: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0
    reason: str = "validation"

    def to_dict(self) -> dict[str, Any]:
        return {"tv_xy_weight": self.tv_xy_weight, "tv_z_weight": self.tv_z_weight, "stage": self.stage,
                "probe_iterations": self.probe_iterations, "trials": self.trials, "seconds": self.seconds, "reason": self.reason}
