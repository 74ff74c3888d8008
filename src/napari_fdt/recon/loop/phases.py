"""The kinds of phase a run's snapshots name (:attr:`napari_fdt.recon.loop.snapshot.Snapshot.phase`).

``"run"``
    The pass: every stage from the first. With ``"auto"`` TV weights the stages before the selection stage run at
    the path's smallest weight (the weight is not known yet) and the selection stage goes on from the winning trial's
    state.
``"tv_choice"``
    The trials of the ``"auto"`` TV weights at the selection stage (:mod:`napari_fdt.recon.choices.tv_search`): one snapshot
    per weight tried (``tv_weights`` set, its ``validation_error`` the trial's). A trial's volume is a candidate, not
    the run's state (the losers' are dropped).
``"rerun"``
    The stages run again from the first with the model parts the data needed (``rerun_with``; ``parts_rerun``
    ``"stages"``).
``"pupil_pilot"``
    Before the first stage, the pupil tried at Δn = 0 (:mod:`napari_fdt.recon.choices.parts_pilot`): a few snapshots of the
    pilot's steps, whose volume is zero (not the run's).

Where the run stands is counted along its plan (:mod:`napari_fdt.recon.loop.plan`): ``plan_iteration`` of
``plan_iterations`` for the whole run, ``phase_iteration`` of ``phase_iterations`` within the phase;
``global_iteration`` / ``total_iterations`` number the stages' iterations as a run without choices would.
"""

from __future__ import annotations

from napari_fdt.recon.loop.regularisation import PROBE_SHARE

__all__ = ["TV_CHOICE", "RUN", "RERUN", "PUPIL_PILOT", "PHASES", "CANDIDATE_PHASES", "phase_label", "probe_iterations"]

TV_CHOICE, RUN, RERUN, PUPIL_PILOT = "tv_choice", "run", "rerun", "pupil_pilot"
PHASES = (PUPIL_PILOT, RUN, TV_CHOICE, RERUN)
#: phases whose snapshots carry no volume of the run (a TV trial's candidate, the pilot's zero): no RI layer or curve point
CANDIDATE_PHASES = (TV_CHOICE, PUPIL_PILOT)


def probe_iterations(stage_iterations: int) -> int:
    """Iterations each TV weight trains for at the selection stage (:data:`~napari_fdt.recon.loop.regularisation.PROBE_SHARE`)."""
    return max(1, int(round(PROBE_SHARE * stage_iterations)))


def phase_label(phase: str, rerun_with: tuple[str, ...] = (), tv_weights: tuple[float, float] | None = None) -> str:
    """The phase in plain English (ASCII)."""
    if phase == TV_CHOICE:
        label = "choosing the smoothing (TV) weight"
        if tv_weights is not None:
            label += f": tried xy {tv_weights[0]:g}, z {tv_weights[1]:g}"
        return label
    if phase == PUPIL_PILOT:
        return "checking the pupil before the stages"
    if phase == RERUN:
        parts = " and ".join(p.replace("_", " ") for p in rerun_with)
        return f"reconstructing again with {parts}" if parts else "reconstructing again"
    return "reconstructing"
