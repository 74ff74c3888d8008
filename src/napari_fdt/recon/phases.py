"""The phases of a run, as its snapshots name them (:attr:`napari_fdt.recon.snapshot.Snapshot.phase`).

A run yields snapshots in up to three phases, in this order:

``"tv_choice"``
    The pilot that chooses the ``"auto"`` TV weights (:mod:`napari_fdt.recon.regularisation`): the stages before the
    selection stage, then one snapshot per weight tried at the selection stage (``tv_weights`` set, its
    ``validation_error`` the trial's). Its stages are run again by the pass: what it yields is progress, not a result.
``"run"``
    The pass: every stage from the first, with the chosen weights.
``"rerun"``
    The stages run again from the first with the model parts the data needed (``rerun_with``; ``parts_rerun``
    ``"stages"``).

``global_iteration`` / ``total_iterations`` number the stage iterations as the pass does in every phase (in the pilot,
a trial snapshot sits at its selection stage's start plus the trial's iterations), so the count starts again with each
phase. ``phase_iteration`` / ``phase_iterations`` count the phase's own work: in the pilot the iterations of the
stages before the selection stage, then :func:`probe_iterations` per weight tried (:class:`PilotPlan`); in the pass and
the rerun they equal ``global_iteration`` / ``total_iterations``.
"""

from __future__ import annotations

from dataclasses import dataclass

from napari_fdt.recon.config import SolverConfig
from napari_fdt.recon.regularisation import PROBE_SHARE, TV_PATH, selection_stages

__all__ = ["TV_CHOICE", "RUN", "RERUN", "PHASES", "PilotPlan", "phase_label", "phase_counts", "pilot_plan", "probe_iterations"]

TV_CHOICE, RUN, RERUN = "tv_choice", "run", "rerun"
PHASES = (TV_CHOICE, RUN, RERUN)


def probe_iterations(stage_iterations: int) -> int:
    """Iterations each TV weight trains for at the selection stage (:data:`~napari_fdt.recon.regularisation.PROBE_SHARE`)."""
    return max(1, int(round(PROBE_SHARE * stage_iterations)))


@dataclass(frozen=True)
class PilotPlan:
    """The pilot's work: the stages before the selection stage ``stage`` (``before`` iterations), then ``probe``
    iterations for each of ``n_trials`` weights."""

    stage: int
    before: int
    probe: int
    n_trials: int

    @property
    def iterations(self) -> int:
        return self.before + self.n_trials * self.probe


def pilot_plan(config: SolverConfig) -> PilotPlan:
    """The pilot of ``config`` (the configuration as run, its stages resolved)."""
    sel = min(selection_stages(config))
    return PilotPlan(sel, sum(s.iterations for s in config.stages[:sel]), probe_iterations(config.stages[sel].iterations),
                     len(TV_PATH))


def phase_counts(config: SolverConfig, phase: str, global_iteration: int, trial: int | None = None) -> tuple[int, int]:
    """(``phase_iteration``, ``phase_iterations``) of a snapshot at ``global_iteration``; ``trial``: the index of the TV
    weight a pilot's trial snapshot has just tried."""
    if phase != TV_CHOICE:
        return global_iteration, config.total_iterations
    plan = pilot_plan(config)
    done = global_iteration if trial is None else plan.before + (trial + 1) * plan.probe
    return done, plan.iterations


def phase_label(phase: str, rerun_with: tuple[str, ...] = (), tv_weights: tuple[float, float] | None = None) -> str:
    """The phase in plain English (ASCII)."""
    if phase == TV_CHOICE:
        label = "choosing the smoothing (TV) weight"
        if tv_weights is not None:
            label += f": tried xy {tv_weights[0]:g}, z {tv_weights[1]:g}"
        return label
    if phase == RERUN:
        parts = " and ".join(p.replace("_", " ") for p in rerun_with)
        return f"reconstructing again with {parts}" if parts else "reconstructing again"
    return "reconstructing"
