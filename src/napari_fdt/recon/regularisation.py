"""Automatic regularisation: the TV weights chosen from the data by the validation error.

With ``tv_xy_weight = "auto"`` (the default; ``tv_z_weight`` likewise) the solver tries a short path of weights
before it trains a stage for good (the rule and its measured cost are in ``docs/solver.md``):

1. At the *selection stage* (:func:`selection_stages`), every candidate of :data:`TV_PATH` trains from the same
   starting state (volume, calibration and their optimisers, batch order: common random numbers, so that the
   candidates differ only by their weight) for a share of the stage's iterations; each ends with the validation
   error of the held-out images (:mod:`napari_fdt.recon.validation`).
2. The one-standard-error rule (:func:`pick`): the largest weight whose validation error is within one standard
   error (over the held-out images) of the lowest. Differences smaller than that are not resolved by the held-out
   images, and among them the smoother volume is the one that does not fill with what the data cannot constrain;
   measured, the plain lowest error regularised less than the RI error wanted on beads, cells and deep sources.
3. The stage then trains from the same starting state with the chosen weight, and so do the later stages.

τ_z follows τ_xy at the ratio :data:`TV_Z_RATIO` when both are ``"auto"``; a weight given as a number stays fixed
while the other is chosen. Without a validation split "auto" means 0 (no TV), with a warning.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from napari_fdt.recon.config import AUTO, SolverConfig

__all__ = ["TV_PATH", "TV_Z_RATIO", "STANDARD_ERRORS", "PROBE_SHARE", "TVChoice", "tv_is_auto", "candidate_weights", "pick",
           "selection_stages"]

#: Candidate lateral TV weights τ_xy, log-spaced over the range where the measured optimum of our scenes lies
#: (docs/ablation.md: from 0 on the bundled sample to about 50 on the authors' demo geometry).
TV_PATH: tuple[float, ...] = (0.0, 1.0, 3.0, 10.0, 30.0, 100.0)
#: τ_z / τ_xy when both are chosen (the issue's "TV 50/25").
TV_Z_RATIO = 0.5
#: Standard errors of the lowest validation error within which a larger weight still counts as good (the
#: one-standard-error rule of cross-validation; Hastie, Tibshirani & Friedman, "Elements of Statistical Learning" §7.10).
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


def pick(trials: list[dict[str, Any]], standard_errors: float = STANDARD_ERRORS) -> dict[str, Any]:
    """The winning trial: of those whose ``validation_error`` is at most the lowest one plus ``standard_errors`` times
    its ``standard_error``, the one with the largest weight (``tau``)."""
    best = min(trials, key=lambda t: t["validation_error"])
    limit = best["validation_error"] + standard_errors * best.get("standard_error", 0.0)
    return max((t for t in trials if t["validation_error"] <= limit), key=lambda t: t["tau"])


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
