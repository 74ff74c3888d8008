"""The start and the end of a run, as ``fdt reconstruct`` and the napari plugin's job both do them.

:func:`open_run` makes the solver: a new run, or one resumed from a checkpoint (a file or a checkpoint folder).
:func:`finish_run` ends it: after a cancel it goes back to the last complete stage (nothing to keep before the first
stage completed) and builds the report (``RI.json``'s content) of what is kept. :func:`add_resolution` then adds the
half-set resolution where ``half_set_resolution`` asks for it (:mod:`napari_fdt.recon.run.half_sets`), after the front end
has written the result: stopping it loses nothing but the figure. :func:`bounds_due` says the same of the error bound
(:mod:`napari_fdt.recon.run.error_bounds`). What each front end then does with
the result (write files, show layers) stays its own.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.errors import FDTInputError
from napari_fdt.recon.settings.config import SolverConfig

if TYPE_CHECKING:
    import torch

    from napari_fdt.recon.problem.distributed import Group
    from napari_fdt.recon.run.solver import Reconstructor

__all__ = ["open_run", "finish_run", "resolution_due", "add_resolution", "bounds_due", "MIN_HALF_SET_IMAGES"]

#: Fewest images the half-set resolution takes: each half a reconstruction of its own.
MIN_HALF_SET_IMAGES = 8


def open_run(acquisition: Acquisition, config: SolverConfig | None, *, device: str | torch.device = "auto",
             resume: str | Path | None = None, initial_sources_um: np.ndarray | None = None,
             group: Group | None = None) -> Reconstructor:
    """The solver of a new run (``config``, ``initial_sources_um``), or of the run a checkpoint holds (``resume``: a
    ``stage_*.pt`` file or a checkpoint folder; the checkpoint's own settings and start positions are used)."""
    from napari_fdt.recon.run.solver import Reconstructor

    if config is not None and config.half_set_resolution and acquisition.n_images < MIN_HALF_SET_IMAGES:
        raise FDTInputError("half_set_resolution", f"needs at least {MIN_HALF_SET_IMAGES} images (two halves of "
                            f"{MIN_HALF_SET_IMAGES // 2}), the acquisition has {acquisition.n_images}",
                            "turn it off, or acquire more images")
    if resume is not None:
        return Reconstructor.from_checkpoint(resume, acquisition, device=device, group=group)
    return Reconstructor(acquisition, config, device=device, initial_sources_um=initial_sources_um, group=group)


def finish_run(rec: Reconstructor, cancelled: bool, **report_kwargs: Any) -> dict[str, Any] | None:
    """End a run: a cancelled one goes back to its last complete stage. Returns the report of what is kept
    (:func:`napari_fdt.recon.run.report.build_report` with ``report_kwargs``), or None when a cancel came before the first
    stage completed (nothing to keep)."""
    from napari_fdt.recon.run.report import build_report

    if cancelled:
        if rec.completed_stages == 0:
            return None
        rec.restore_last_complete()
    return build_report(rec, cancelled=cancelled, **report_kwargs)


def resolution_due(rec: Reconstructor, cancelled: bool) -> bool:
    """Whether the half-set resolution is to be estimated: asked for (``half_set_resolution``), the run ended, and one
    process ran it (a data-parallel run's halves are not estimated: rerun the result's settings in one process)."""
    return (bool(rec.config.half_set_resolution) and not cancelled and rec.group is None
            and rec.completed_stages == len(rec.config.stages))


def bounds_due(rec: Reconstructor, cancelled: bool) -> bool:
    """Whether the per-voxel error bound is to be made (``error_bounds``; :mod:`napari_fdt.recon.run.error_bounds`):
    asked for, the run ended, and one process ran it."""
    return (bool(rec.config.error_bounds) and not cancelled and rec.group is None
            and rec.completed_stages == len(rec.config.stages))


def add_resolution(rec: Reconstructor, report: dict[str, Any], *, should_stop=None, on_half=None) -> dict[str, Any] | None:
    """``report`` with its ``resolution`` section (:func:`napari_fdt.recon.run.half_sets.half_set_resolution`), or None
    when ``should_stop`` stopped a half (the report stands as it was)."""
    from napari_fdt.recon.run.half_sets import half_set_resolution

    estimate = half_set_resolution(rec, should_stop=should_stop, on_half=on_half)
    return None if estimate is None else {**report, "resolution": estimate.to_dict()}
