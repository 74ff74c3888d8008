"""Checkpoints of a reconstruction: the state at the end of a stage, written atomically, and read back to resume.

A checkpoint (``stage_<i>.pt``, ``torch.save`` of a dict; ``format`` ``"napari-fdt-checkpoint"``, version 2)
holds plain data only: dicts, lists, tuples, strings, numbers, booleans, None and tensors (a NumPy array as
``{"__ndarray__": tensor}``). It is read with ``torch.load(..., weights_only=True)``, whose unpickler builds those
types and nothing else, so a file from elsewhere cannot run code when it is resumed (a pickle of any other object is
refused before anything of it is made; docs/format.md, "Checkpoints"). It holds the configuration, the completed
stages (and, written inside a stage, ``in_stage``: that stage's progress, :func:`in_stage_state`), the RI grid, the
calibration parameters and their Adam state (:meth:`~napari_fdt.recon.calibration.calibration.Calibration.state_dict`, its keys at the top level), the batch
order, the stage records, the history and the elapsed time, and the acquisition's size (checked on resume).
"""

from __future__ import annotations

import dataclasses
import pickle
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.errors import FDTInputError
from napari_fdt.recon.loop.snapshot import StageRecord

if TYPE_CHECKING:
    from napari_fdt.recon.loop.interface import Run

__all__ = ["FORMAT", "VERSION", "checkpoint_path", "in_stage_path", "prune_in_stage", "in_stage_state", "resume_in_stage",
           "has_checkpoint", "latest_checkpoint", "checkpoint_state", "write_checkpoint", "read_checkpoint", "restore_checkpoint"]

FORMAT = "napari-fdt-checkpoint"
#: Version 2 (2026-11-27): plain data only, read without unpickling objects. Version 1 held a NumPy array and the stage
#: records as pickled objects, so it cannot be read safely; :func:`read_checkpoint` refuses it with the fix.
VERSION = 2
_NDARRAY = "__ndarray__"


def _plain(obj: Any, where: str = "checkpoint") -> Any:
    """``obj`` as plain data (what ``torch.load(weights_only=True)`` rebuilds): NumPy arrays as ``{"__ndarray__":
    tensor}``, NumPy scalars as Python numbers; TypeError naming the path of anything else (a bug: a checkpoint must
    never need the unpickler to make an object)."""
    if obj is None or isinstance(obj, (bool, int, float, str, torch.Tensor)):
        return obj
    if isinstance(obj, np.ndarray):
        return {_NDARRAY: torch.from_numpy(np.ascontiguousarray(obj).copy())}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, dict):
        for k in obj:
            if not isinstance(k, (str, int)):
                raise TypeError(f"{where}: key {k!r} is a {type(k).__name__}, not a string or an integer")
        return {k: _plain(v, f"{where}.{k}") for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        out = [_plain(v, f"{where}[{i}]") for i, v in enumerate(obj)]
        return out if isinstance(obj, list) else tuple(out)
    raise TypeError(f"{where} is a {type(obj).__module__}.{type(obj).__name__}: a checkpoint holds plain data and tensors only")


def _from_plain(obj: Any) -> Any:
    """The inverse of :func:`_plain` (NumPy arrays back)."""
    if isinstance(obj, dict):
        if set(obj) == {_NDARRAY} and isinstance(obj[_NDARRAY], torch.Tensor):
            return obj[_NDARRAY].numpy()
        return {k: _from_plain(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_from_plain(v) for v in obj]
    if isinstance(obj, tuple):
        return tuple(_from_plain(v) for v in obj)
    return obj


def checkpoint_path(directory: str | Path, stage_index: int) -> Path:
    """Where the checkpoint of stage ``stage_index`` goes in ``directory``: ``stage_<i>.pt``."""
    return Path(directory) / f"stage_{stage_index}.pt"


def in_stage_path(directory: str | Path, stage_index: int, iteration: int) -> Path:
    """Where a checkpoint inside stage ``stage_index`` after ``iteration`` of its iterations goes: ``stage_<i>_it<k>.pt``."""
    return Path(directory) / f"stage_{stage_index}_it{iteration}.pt"


def prune_in_stage(directory: str | Path, keep: Path | None = None) -> None:
    """Delete the checkpoints written inside stages (``stage_*_it*.pt``) but ``keep``: a newer one, or the stage's end,
    holds all they held."""
    for p in Path(directory).glob("stage_*_it*.pt"):
        if keep is None or p.resolve() != Path(keep).resolve():
            p.unlink(missing_ok=True)


def _capture_out(capture: Any) -> Any:
    """A capture of the solver's state (``_capture``, ``capture_branch``) with its stage records as dicts (plain data)."""
    if isinstance(capture, dict) and "stages" in capture:
        return {**capture, "stages": [r.to_dict() for r in capture["stages"]]}
    return capture


def _capture_in(capture: Any) -> Any:
    """The inverse of :func:`_capture_out`."""
    if isinstance(capture, dict) and "stages" in capture:
        return {**capture, "stages": [StageRecord.from_dict(r) for r in capture["stages"]]}
    return capture


def in_stage_state(work: Any, now: float) -> dict[str, Any]:
    """What a checkpoint inside a stage adds to the run's state: the stage's iterations done, its RI optimiser, its
    best iterate so far, its record, what its choices marked (the state to start it again from) and its seconds."""
    best = work.best
    return {"stage": work.stage.index, "done": work.done, "optimiser": work.optimiser.state_dict(),
            "best": {"best_error": best.best_error, "best_iteration": best.best_iteration, "state": _capture_out(best.state),
                     "errors": list(best.errors)},
            "record": work.record.to_dict(), "choosing": {k: _capture_out(v) for k, v in work.choosing.items()}, "stage_seconds": now - work.t0,
            "terms": work.terms, "train_error": work.train_error}


def resume_in_stage(rec: Run, work: Any, state: dict[str, Any]) -> None:
    """Put :func:`in_stage_state`'s ``state`` back into the stage ``work`` just begun (its record replaces the new one
    in ``rec.stages``); the stage then goes on after ``state["done"]`` iterations."""
    work.optimiser.load_state_dict(state["optimiser"])
    work.done, work.resumed = int(state["done"]), True
    b = state["best"]
    work.best.best_error, work.best.best_iteration, work.best.state, work.best.errors = (
        b["best_error"], b["best_iteration"], _capture_in(b["state"]), list(b["errors"]))
    work.record = StageRecord.from_dict(state["record"])
    rec.stages = [r for r in rec.stages if r.stage != work.stage.index] + [work.record]
    work.choosing = {k: _capture_in(v) for k, v in state["choosing"].items()}
    work.terms, work.train_error = dict(state["terms"]), state["train_error"]
    work.t0 = time.perf_counter() - float(state["stage_seconds"])


def _checkpoints(directory: str | Path) -> list[Path]:
    """The complete checkpoints in ``directory`` (``stage_*.pt``; one being written is a hidden ``.tmp``)."""
    return [p for p in Path(directory).glob("stage_*.pt") if p.is_file()]


def has_checkpoint(directory: str | Path) -> bool:
    """Whether ``directory`` holds a complete checkpoint (False where it does not exist)."""
    return bool(_checkpoints(directory))


def latest_checkpoint(directory: str | Path) -> Path:
    """The checkpoint in ``directory`` written last (``stage_<i>.pt``; a file being written is a hidden ``.tmp`` until it
    is complete, so it is never picked). By write time, not by stage number: when a choice runs the stages again from
    the first, ``stage_0.pt`` of the second pass is newer than ``stage_1.pt`` of the first."""
    found = _checkpoints(directory)
    if not found:
        raise FDTInputError("resume", f"{directory} holds no checkpoint (stage_*.pt)",
                            "point --resume at the folder given to --checkpoint-dir, or at one of its stage_*.pt files")
    return max(found, key=lambda p: (p.stat().st_mtime_ns, p.name))


def checkpoint_state(rec: Run) -> dict[str, Any]:
    """The state of ``rec`` as a checkpoint dict (tensors on the CPU): its :class:`~napari_fdt.recon.loop.run_state.RunState`,
    the configuration, the initial sources and the acquisition's size."""
    return {
        "format": FORMAT, "version": VERSION, "config": rec.requested_config.to_dict(),
        **rec.state.state_dict(),
        "initial_sources_um": rec.initial_sources_um, "n_images": rec.acquisition.n_images,
        "image_shape": list(rec.full_shape),
    }


def write_checkpoint(state: dict[str, Any], path: str | Path) -> Path:
    """Write ``state`` to ``path`` atomically (temporary file in the same folder, then rename); returns the path.
    ``state`` must be plain data and tensors (NumPy arrays and scalars are converted; anything else is a TypeError)."""
    path = Path(path)
    plain = _plain(state)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    torch.save(plain, tmp)
    tmp.replace(path)
    return path


def read_checkpoint(path: str | Path, acquisition: Acquisition) -> dict[str, Any]:
    """Read a checkpoint (a ``stage_<i>.pt`` file, or a checkpoint folder: its :func:`latest_checkpoint`) and check that
    it belongs to an acquisition of ``acquisition``'s size (FDTInputError if not).

    The file is read with ``weights_only=True``: only plain data and tensors are built, so a crafted file cannot run
    code; one that holds any other object (a pickle from elsewhere, or a version-1 checkpoint) is refused with the fix."""
    if Path(path).is_dir():
        path = latest_checkpoint(path)
    try:
        state = torch.load(Path(path), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:  # an object other than plain data and tensors: nothing of it was made or run
        raise FDTInputError(
            "resume", f"{path} holds Python objects other than data and tensors, so it was not read (no code in it ran): "
            "it is not a checkpoint of this napari-fdt version (a version-1 checkpoint, written before 2026-11-27, or a "
            "file from elsewhere)",
            "start the run afresh without --resume; a version-1 checkpoint you wrote yourself resumes with the napari-fdt "
            "that wrote it") from None
    except Exception as exc:  # noqa: BLE001 (torch.load raises OSError, RuntimeError, EOFError … on a bad file)
        raise FDTInputError("resume", f"cannot read checkpoint {path}: {exc}", "point --resume at a stage_*.pt file") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise FDTInputError("resume", f"{path} is not a napari-fdt checkpoint", "point --resume at a stage_*.pt file")
    if state.get("version") != VERSION:
        raise FDTInputError("resume", f"{path} is a version-{state.get('version')} checkpoint; this napari-fdt reads version {VERSION}",
                            "start the run afresh without --resume, or resume it with the napari-fdt that wrote it")
    state = _from_plain(state)
    if state["n_images"] != acquisition.n_images or tuple(state["image_shape"]) != acquisition.image_shape:
        raise FDTInputError("resume", "the checkpoint belongs to an acquisition of another size", "resume with the same acquisition")
    return state


def restore_checkpoint(rec: Run, state: dict[str, Any]) -> None:
    """Put a checkpoint's state into ``rec`` (made with the checkpoint's configuration and initial sources): the parts
    choice first (it switches the calibration's parameters), then the :class:`~napari_fdt.recon.loop.run_state.RunState`,
    then the loss weights of the chosen TV weights."""
    from napari_fdt.recon.loop.model_parts import PartsChoice

    rec._resume_in_stage = state.get("in_stage")  # a checkpoint written inside a stage: that stage goes on where it was
    rec.completed_stages = int(state["completed_stages"])
    parts = state.get("parts_choice")  # absent before the choice (and in checkpoints written before it existed)
    if parts is not None:
        rec.apply_parts_choice(PartsChoice.from_dict(parts))
    rec.state.load_state_dict(state, rec.device, rec.dtype)
    if rec.tv_choice is not None:
        rec.loss_weights = dataclasses.replace(rec.loss_weights, tv_xy=rec.tv_choice.tv_xy_weight, tv_z=rec.tv_choice.tv_z_weight)
