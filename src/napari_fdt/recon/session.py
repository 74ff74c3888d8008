"""The start and the end of a run, as ``fdt reconstruct`` and the napari plugin's job both do them.

:func:`open_run` makes the solver: a new run, or one resumed from a checkpoint (a file or a checkpoint folder).
:func:`finish_run` ends it: after a cancel it goes back to the last complete stage (nothing to keep before the first
stage completed) and builds the report (``RI.json``'s content) of what is kept. What each front end then does with
the result (write files, show layers) stays its own.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.recon.config import SolverConfig

if TYPE_CHECKING:
    import torch

    from napari_fdt.recon.distributed import Group
    from napari_fdt.recon.solver import Reconstructor

__all__ = ["open_run", "finish_run"]


def open_run(acquisition: Acquisition, config: SolverConfig | None, *, device: str | torch.device = "auto",
             resume: str | Path | None = None, initial_sources_um: np.ndarray | None = None,
             group: Group | None = None) -> Reconstructor:
    """The solver of a new run (``config``, ``initial_sources_um``), or of the run a checkpoint holds (``resume``: a
    ``stage_*.pt`` file or a checkpoint folder; the checkpoint's own settings and start positions are used)."""
    from napari_fdt.recon.solver import Reconstructor

    if resume is not None:
        return Reconstructor.from_checkpoint(resume, acquisition, device=device, group=group)
    return Reconstructor(acquisition, config, device=device, initial_sources_um=initial_sources_um, group=group)


def finish_run(rec: Reconstructor, cancelled: bool, **report_kwargs: Any) -> dict[str, Any] | None:
    """End a run: a cancelled one goes back to its last complete stage. Returns the report of what is kept
    (:func:`napari_fdt.recon.report.build_report` with ``report_kwargs``), or None when a cancel came before the first
    stage completed (nothing to keep)."""
    from napari_fdt.recon.report import build_report

    if cancelled:
        if rec.completed_stages == 0:
            return None
        rec.restore_last_complete()
    return build_report(rec, cancelled=cancelled, **report_kwargs)
