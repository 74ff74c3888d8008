"""The reconstruction widget's line before a run: what Reconstruct would take, from the plan ``fdt plan`` prints
(:func:`napari_fdt.recon.loop.plan.plan_for`; its range where the data choose the TV weight and the model parts).
No Qt here."""

from __future__ import annotations

import numpy as np

from napari_fdt.errors import FDTInputError
from napari_fdt.recon.settings.config import SolverConfig

__all__ = ["PLAN_PREFIX", "plan_line"]

#: How the line starts (the widget replaces only a status that is empty or one of these lines).
PLAN_PREFIX = "Reconstruct would take"


def plan_line(acquisition, config: SolverConfig, device: str, sources_um: np.ndarray | None) -> str:
    """"Reconstruct would take about 30 s on cpu; up to about 4 min as the data choose …", or "" where the plan cannot
    be made in a few milliseconds: no source positions yet (their fit takes seconds) or settings it refuses (the run
    will say why). ``device``: the widget's choice ("auto", "cpu", "cuda")."""
    from napari_fdt.device import resolve_device
    from napari_fdt.recon.loop.plan import plan_for, seconds_in_words

    if sources_um is None and acquisition.sources_um is None:
        return ""
    try:
        dev = resolve_device(device).type
        plan, _ = plan_for(acquisition, config, dev, sources_um)
    except (FDTInputError, ValueError):
        return ""
    after = [(s, what) for s, what in ((plan.half_sets_s, "the resolution's half runs"), (plan.bounds_s, "the error bound's runs"))
             if s is not None]  # asked for: they run after the reconstruction
    extra = sum(s for s, _ in after)
    line = f"{PLAN_PREFIX} about {seconds_in_words(plan.predicted_s + extra)} on {dev}"
    if after:
        line += f" (with {' and '.join(what for _, what in after)})"
    if plan.range_top_s is not None:
        line += f"; up to about {seconds_in_words(plan.range_top_s + extra)} as the data choose the smoothing and the model parts"
    return line + " (fdt plan)."
