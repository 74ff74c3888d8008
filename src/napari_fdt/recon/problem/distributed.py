"""Data-parallel reconstruction with ``torch.distributed``: one process per device, the sources shared out.

Launched by ``torchrun`` (which sets ``WORLD_SIZE``, ``RANK``, ``LOCAL_RANK``, ``MASTER_ADDR``,
``MASTER_PORT``), :func:`setup` joins the process group and returns a :class:`Group`; without those
variables, or with ``WORLD_SIZE=1``, it returns None and nothing here has any effect. ``docs/distributed.md``
has the launch recipes.

How the work is shared (the solver calls the methods of :class:`Group`):

* Image ``i`` belongs to rank ``i % world_size`` (:func:`owned`). Every rank draws the same global batch
  (same seeded generator) and keeps the images it owns; a rank may own none of a batch and still takes part
  in every collective.
* The loss of each rank is normalised by the whole batch (:class:`~napari_fdt.recon.problem.losses.BatchShare`), so the
  ranks' losses add up to the single-process loss, and the summed gradients of the shared parameters (the
  RI grid, the global optical scalars) are the single-process gradients: :meth:`Group.reduce_gradients`
  sums them in one all-reduce.
* Per-source parameters (positions, gains) are full-size tensors on every rank, but only the rows a rank
  owns are kept up to date there (Adam is elementwise, and the gradient of a row comes only from its
  image). :meth:`Group.share_rows` copies each row from its owner to every rank before anything reads all
  rows (snapshots, stage ends, checkpoints, the output).
* What assesses the state (held-out errors, the parts' tests, the TV trials' choice, the pupil's pilot) is shared
  out the same way: each rank predicts the images it owns and the per-image sums are added
  (:func:`napari_fdt.recon.loop.run_validation.image_errors`), so every rank decides on the same numbers.
* Rank 0 alone writes outputs and checkpoints and prints progress.

Backends: NCCL when the rank's device is a CUDA device and each rank has a GPU of its own; gloo otherwise
(CPU, or several ranks sharing one GPU, which NCCL refuses). ``FDT_DIST_BACKEND`` (or ``fdt reconstruct
--dist-backend``) overrides the choice. ``FDT_DIST_TIMEOUT_S`` (default 1800) bounds how long a rank waits
in a collective for the others, so an error on one rank cannot hang the rest for ever.
"""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass
from typing import Mapping, Sequence

import torch

from napari_fdt.errors import FDTInputError

__all__ = ["Group", "BACKENDS", "world_from_env", "owned", "choose_backend", "rank_device", "setup", "teardown"]

BACKENDS = ("auto", "nccl", "gloo")
#: Seconds a rank waits in a collective before giving up (``FDT_DIST_TIMEOUT_S`` overrides).
DEFAULT_TIMEOUT_S = 1800.0


def world_from_env(env: Mapping[str, str] | None = None) -> tuple[int, int, int, int]:
    """``(world_size, rank, local_rank, local_world_size)`` from torchrun's variables; ``(1, 0, 0, 1)`` when not launched."""
    env = os.environ if env is None else env

    def integer(name: str, default: int | None) -> int:
        value = env.get(name)
        if value is None or value == "":
            if default is None:
                raise FDTInputError(name, "is not set, but WORLD_SIZE > 1 says this is a distributed launch",
                                    "launch with torchrun (docs/distributed.md), which sets it")
            return default
        try:
            return int(value)
        except ValueError:
            raise FDTInputError(name, f"must be an integer, got {value!r}", "launch with torchrun (docs/distributed.md)") from None

    world = integer("WORLD_SIZE", 1)
    if world < 1:
        raise FDTInputError("WORLD_SIZE", f"must be >= 1, got {world}", "launch with torchrun (docs/distributed.md)")
    if world == 1:
        return 1, 0, 0, 1
    rank = integer("RANK", None)
    local_rank = integer("LOCAL_RANK", rank)
    local_world = integer("LOCAL_WORLD_SIZE", world)
    if not 0 <= rank < world:
        raise FDTInputError("RANK", f"must be in 0..{world - 1}, got {rank}", "launch with torchrun (docs/distributed.md)")
    return world, rank, local_rank, local_world


def owned(indices, rank: int, world_size: int):
    """The entries of ``indices`` (image numbers; a tensor or a numpy array, the same kind back) that ``rank`` owns
    (``i % world_size == rank``), in their order."""
    return indices[indices % world_size == rank]


def choose_backend(device: torch.device, requested: str | None = None, *, ranks_per_gpu: int = 1) -> str:
    """``"nccl"`` or ``"gloo"``.

    ``requested``: ``"auto"``/None (then ``FDT_DIST_BACKEND`` if set), ``"nccl"`` or ``"gloo"``. Auto is NCCL
    for CUDA devices when no two ranks share a GPU (NCCL refuses that) and NCCL is built in, else gloo.
    """
    choice = (requested or "auto").lower()
    source = "--dist-backend"
    if choice == "auto" and os.environ.get("FDT_DIST_BACKEND"):
        choice, source = os.environ["FDT_DIST_BACKEND"].lower(), "FDT_DIST_BACKEND"
    if choice not in BACKENDS:
        raise FDTInputError(source, f"unknown backend {choice!r}", f"choose one of {', '.join(BACKENDS)}")
    if choice == "nccl" and device.type != "cuda":
        raise FDTInputError(source, f"NCCL needs CUDA devices, this rank runs on {device}", "use gloo on CPU")
    if choice != "auto":
        return choice
    if device.type == "cuda" and ranks_per_gpu == 1 and torch.distributed.is_nccl_available():
        return "nccl"
    return "gloo"


def rank_device(device: str | torch.device, local_rank: int, gpu_count: int | None = None) -> torch.device:
    """The device of one rank: ``cuda:(LOCAL_RANK mod GPUs)`` for ``"auto"``/``"cuda"`` on a CUDA machine, else as given.

    An explicit ``cuda:K`` is kept (every rank of the machine then uses GPU K).
    """
    from napari_fdt import device as _device

    dev = _device.resolve_device(device)
    if dev.type != "cuda" or dev.index is not None:
        return dev
    count = torch.cuda.device_count() if gpu_count is None else gpu_count
    return torch.device("cuda", local_rank % max(1, count))


@dataclass(frozen=True)
class Group:
    """This process's place in a data-parallel reconstruction (made by :func:`setup`)."""

    rank: int
    world_size: int
    local_rank: int
    backend: str
    device: torch.device

    @property
    def is_writer(self) -> bool:
        """Whether this rank writes outputs, checkpoints and progress (rank 0)."""
        return self.rank == 0

    def describe(self) -> dict[str, object]:
        """For the report."""
        return {"world_size": self.world_size, "backend": self.backend, "image_owner": "image i -> rank i % world_size"}

    def local(self, indices):
        """The images of a global batch that this rank works on (a tensor or a numpy array, the same kind back)."""
        return owned(indices, self.rank, self.world_size)

    def _all_reduce(self, flat: torch.Tensor, op=None) -> torch.Tensor:
        """Sum (or ``op``) over ranks of a flat tensor; gloo reduces a CUDA tensor through a CPU copy."""
        import torch.distributed as dist

        op = dist.ReduceOp.SUM if op is None else op
        if self.backend == "gloo" and flat.device.type != "cpu":
            host = flat.cpu()
            dist.all_reduce(host, op=op)
            return host.to(flat.device)
        dist.all_reduce(flat, op=op)
        return flat

    def sum(self, values: torch.Tensor) -> torch.Tensor:
        """``values`` summed over ranks (every rank must call this with the same shape; the same result on all)."""
        return self._all_reduce(values.clone())

    def any(self, flag: bool) -> bool:
        """Whether ``flag`` is true on any rank (every rank must call this)."""
        import torch.distributed as dist

        t = torch.tensor([1.0 if flag else 0.0], device=self.device)
        return bool(self._all_reduce(t, dist.ReduceOp.MAX).item() > 0)

    def reduce_gradients(self, shared: Sequence[torch.Tensor], per_source: Sequence[torch.Tensor]) -> None:
        """After ``backward``: sum the gradients of the ``shared`` parameters over ranks; keep ``per_source`` ones local.

        A parameter with no gradient on this rank (its graph did not reach it, e.g. no image in this batch)
        gets zeros if any rank has one, so that every rank's optimiser steps every parameter that the
        single-process run would step (Adam skips a parameter whose ``grad`` is None), and keeps None if no
        rank has one. One all-reduce carries these flags and all shared gradients.
        """
        shared = [p for p in shared if p.requires_grad]
        per_source = [p for p in per_source if p.requires_grad]
        params = shared + per_source
        if not params:
            return
        ref = params[0]
        flags = torch.tensor([0.0 if p.grad is None else 1.0 for p in params], device=ref.device, dtype=ref.dtype)
        parts = [flags] + [(torch.zeros_like(p) if p.grad is None else p.grad).reshape(-1) for p in shared]
        flat = self._all_reduce(torch.cat(parts))
        present = (flat[: len(params)] > 0).tolist()
        offset = len(params)
        for p, has in zip(shared, present):
            n = p.numel()
            p.grad = flat[offset: offset + n].view_as(p) if has else None
            offset += n
        for p, has in zip(per_source, present[len(shared):]):
            if has and p.grad is None:
                p.grad = torch.zeros_like(p)

    def share_rows(self, tensors: Sequence[torch.Tensor]) -> None:
        """In place: row ``i`` of each tensor (first axis = image) becomes its owner's row on every rank.

        Each rank contributes its own rows and zeros elsewhere to one summed all-reduce (adding zeros is
        exact, so owned rows keep their bits).
        """
        tensors = [t for t in tensors if t is not None]
        if not tensors:
            return
        with torch.no_grad():
            parts = []
            for t in tensors:
                rows = torch.arange(t.shape[0], device=t.device) % self.world_size == self.rank
                mask = rows.reshape(-1, *([1] * (t.ndim - 1)))
                parts.append(torch.where(mask, t, torch.zeros_like(t)).reshape(-1).to(torch.float64))
            flat = self._all_reduce(torch.cat(parts))
            offset = 0
            for t in tensors:
                n = t.numel()
                t.copy_(flat[offset: offset + n].view_as(t))
                offset += n

    def sum_terms(self, terms: dict[str, torch.Tensor], keys: Sequence[str]) -> dict[str, torch.Tensor]:
        """``terms`` with the entries named in ``keys`` summed over ranks (every rank must hold the same keys)."""
        names = [k for k in keys if k in terms]
        if not names:
            return dict(terms)
        flat = self._all_reduce(torch.stack([terms[k].detach().to(torch.float64) for k in names]))
        out = dict(terms)
        for k, v in zip(names, flat.unbind()):
            out[k] = v.to(terms[k].dtype)
        return out


def setup(device: str | torch.device = "auto", backend: str | None = None, *, timeout_s: float | None = None) -> Group | None:
    """Join the process group of a torchrun launch; None (and nothing done) when not launched distributed.

    The device of each rank is :func:`rank_device` of ``device``; the backend :func:`choose_backend`.
    """
    world, rank, local_rank, local_world = world_from_env()
    if world == 1:
        return None
    import torch.distributed as dist

    if not dist.is_available():
        raise FDTInputError("WORLD_SIZE", "this torch build has no torch.distributed", "run one process, or install a torch with it")
    for name in ("MASTER_ADDR", "MASTER_PORT"):
        if not os.environ.get(name):
            raise FDTInputError(name, "is not set, but WORLD_SIZE > 1 says this is a distributed launch",
                                "launch with torchrun (docs/distributed.md), which sets it")
    dev = rank_device(device, local_rank)
    gpus = torch.cuda.device_count() if dev.type == "cuda" else 0
    per_gpu = -(-local_world // gpus) if gpus else 1
    name = choose_backend(dev, backend, ranks_per_gpu=per_gpu)
    if timeout_s is None:
        raw = os.environ.get("FDT_DIST_TIMEOUT_S", "")
        try:
            timeout_s = float(raw) if raw else DEFAULT_TIMEOUT_S
        except ValueError:
            raise FDTInputError("FDT_DIST_TIMEOUT_S", f"must be a number of seconds, got {raw!r}", "e.g. 1800") from None
    if not timeout_s > 0:
        raise FDTInputError("FDT_DIST_TIMEOUT_S", f"must be > 0, got {timeout_s}", "e.g. 1800")
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    dist.init_process_group(name, timeout=datetime.timedelta(seconds=timeout_s))
    return Group(rank=rank, world_size=world, local_rank=local_rank, backend=name, device=dev)


def teardown(group: Group | None, completed: bool = False) -> None:
    """Leave the process group (nothing when ``group`` is None).

    ``completed``: every rank ended its run and reaches this call; they first wait for each other, so that no rank
    tears down its connections while a peer still writes or holds them (a gloo rank leaving early was seen to abort
    at exit, "terminate called without an active exception", after a run that had written its result). After a
    failure the ranks leave at once (a peer may be gone)."""
    if group is None:
        return
    import torch.distributed as dist

    if dist.is_initialized():
        if completed:
            try:
                if group.backend == "gloo":
                    dist.monitored_barrier(timeout=datetime.timedelta(seconds=120))
                else:
                    dist.barrier()
            except Exception:  # noqa: BLE001 (a peer that is gone: leave anyway)
                pass
        dist.destroy_process_group()
