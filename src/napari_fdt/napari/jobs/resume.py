"""Checkpoints of the plugin's runs, and the offer to resume an interrupted one (no Qt here).

Every reconstruction the widget starts on an acquisition read from a folder writes its checkpoints
(:mod:`napari_fdt.recon.loop.checkpoint`: at each stage's end and every ``checkpoint_every_s`` inside a stage) to a folder of
the user's cache that belongs to that acquisition folder: ``$NAPARI_FDT_CHECKPOINTS`` if set, else
``$XDG_CACHE_HOME/napari-fdt/checkpoints`` (``~/.cache/…``), one sub-folder per acquisition path. A run that ends
normally deletes them; a run that was cancelled, or whose process or napari died, leaves them, and the widget offers to
resume it (:func:`interrupted_run`) when that acquisition is selected again. The input folder is never written to.
"""

from __future__ import annotations

import datetime
import hashlib
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

from napari_fdt.recon.loop.checkpoint import latest_checkpoint

__all__ = ["ResumeOffer", "checkpoint_folder", "interrupted_run", "clear"]

_STAGE = re.compile(r"stage_(\d+)(?:_it(\d+))?\.pt$")


def _root() -> Path:
    given = os.environ.get("NAPARI_FDT_CHECKPOINTS")
    if given:
        return Path(given)
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "napari-fdt" / "checkpoints"


def checkpoint_folder(acquisition_path: str | os.PathLike | None) -> Path | None:
    """The folder the plugin's runs of the acquisition at ``acquisition_path`` checkpoint to (None without a path:
    an acquisition made in memory, e.g. simulated or edited, has no place to be found again)."""
    if not acquisition_path:
        return None
    resolved = str(Path(acquisition_path).expanduser().resolve())
    key = hashlib.sha1(resolved.encode("utf-8")).hexdigest()[:16]
    return _root() / f"{Path(resolved).name or 'acquisition'}-{key}"


@dataclass(frozen=True)
class ResumeOffer:
    """An interrupted run found in ``folder``: its latest checkpoint, how far it got and when it was written."""

    folder: Path
    latest: Path
    stages_done: int
    in_stage_iteration: int | None
    saved_at: datetime.datetime

    def describe(self) -> str:
        """e.g. "stage 2 done, in stage 3 at iteration 80; saved 14:02 (Nov 26)"."""
        where = f"{self.stages_done} stage{'s' if self.stages_done != 1 else ''} done"
        if self.in_stage_iteration is not None:
            where += f", in stage {self.stages_done + 1} at iteration {self.in_stage_iteration}"
        return f"{where}; saved {self.saved_at:%H:%M (%b %d)}"

    def short(self) -> str:
        """e.g. "1 stage done, 14:02" or "stage 3, it. 80, 14:02": what fits beside a checkbox in a docked widget."""
        where = (f"{self.stages_done} stage{'s' if self.stages_done != 1 else ''} done" if self.in_stage_iteration is None
                 else f"stage {self.stages_done + 1}, it. {self.in_stage_iteration}")
        return f"{where}, {self.saved_at:%H:%M}"


def interrupted_run(folder: Path | None) -> ResumeOffer | None:
    """The interrupted run whose checkpoints ``folder`` holds, or None (no folder, or no checkpoint in it)."""
    if folder is None or not folder.is_dir() or not any(p.is_file() for p in folder.glob("stage_*.pt")):
        return None
    latest = latest_checkpoint(folder)  # the one resuming picks
    match = _STAGE.search(latest.name)
    if match is None:
        return None
    stage, iteration = match.groups()
    done = int(stage) + 1 if iteration is None else int(stage)
    return ResumeOffer(folder, latest, done, None if iteration is None else int(iteration),
                       datetime.datetime.fromtimestamp(latest.stat().st_mtime))


def clear(folder: Path | None) -> None:
    """Delete the checkpoints of ``folder`` (a run that ended, or one started afresh); the folder goes with them."""
    if folder is not None and folder.is_dir():
        shutil.rmtree(folder, ignore_errors=True)
