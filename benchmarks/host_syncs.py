"""Operations in one solver iteration that make the host wait for a GPU, counted on the CPU (docs/benchmarks.md,
GPU checklist item 6).

    python -m benchmarks run host_syncs [--acquisition DIR] [--field-window full|split] [--steps 20]

On CUDA the host queues an iteration's ~200 kernels ahead of the GPU unless an operation needs a result on the host:
a Python number from a tensor (``item``, ``float``, ``bool``, ``int``: ``aten._local_scalar_dense``), an output whose
size depends on the data (``nonzero``, a boolean-mask index, ``masked_select``, ``unique``), or a LAPACK-style
routine that checks its status on the host (``linalg.eigh``, ``linalg.cholesky``, ...). Each such wait exposes the
host's launch time of the work that follows it. This counts them with a ``TorchDispatchMode`` (the same operators
run on the CPU; no GPU needed) in ``Reconstructor._step`` of an acquisition's finest stage (default: the bundled
sample, the full field window as on CUDA, the sources' positions trained), and names the Python line of each.
:func:`count_syncs` is also what ``tests/test_host_syncs.py`` asserts on. The solver's iteration on an H200 took
28.4 ms against 15.6 ms for the model's step (docs/decisions/gpu-checklist-h200.md): these waits are one suspect.
"""

from __future__ import annotations

import argparse
import collections
import traceback
from pathlib import Path
from typing import Callable

import torch
from torch.utils._python_dispatch import TorchDispatchMode

ROOT = Path(__file__).resolve().parents[1]

#: operators whose result the host must read (or whose output size depends on the data) on CUDA
SYNC_OPS = ("_local_scalar_dense", "nonzero", "masked_select", "_unique", "_unique2", "unique_dim", "unique_consecutive",
            "repeat_interleave", "_linalg_eigh", "linalg_eigh", "_linalg_check_errors", "linalg_cholesky_ex",
            "linalg_inv_ex", "linalg_solve_ex", "equal", "is_nonzero")
_INDEX_OPS = ("index", "index_put", "index_put_", "_index_put_impl_")


def _is_bool_index(func, args) -> bool:
    if func.__name__.split(".")[0] not in _INDEX_OPS or len(args) < 2:
        return False
    return any(isinstance(i, torch.Tensor) and i.dtype in (torch.bool, torch.uint8) for i in (args[1] or ()))


class SyncCounter(TorchDispatchMode):
    """Counts the operators of :data:`SYNC_OPS` and boolean-mask indexing, each with the package's (or the
    benchmark's) Python line that called it."""

    def __init__(self) -> None:
        super().__init__()
        self.sites: collections.Counter = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.__name__.split(".")[0]
        if name in SYNC_OPS or _is_bool_index(func, args):
            stack = traceback.extract_stack()[:-1]
            ours = [i for i, f in enumerate(stack) if "napari_fdt" in f.filename or "benchmarks" in f.filename]
            site = stack[ours[-1]] if ours else None
            # torch.optim's own step counters live in host memory (not ``capturable``): reading them waits for
            # nothing on CUDA either, so an operator called from inside torch.optim below our line is not counted
            inner = stack[ours[-1] + 1:] if ours else stack
            if not any("torch/optim/" in f.filename for f in inner):
                key = f"{site.filename.split('src/')[-1]}:{site.lineno} ({site.name})" if site else "?"
                self.sites[(name, key)] += 1
        return func(*args, **(kwargs or {}))

    @property
    def total(self) -> int:
        return sum(self.sites.values())


def count_syncs(step: Callable[[], object], steps: int) -> SyncCounter:
    """Run ``step`` ``steps`` times under a :class:`SyncCounter`; return it (``total / steps`` per iteration)."""
    counter = SyncCounter()
    with counter:
        for _ in range(steps):
            step()
    return counter


def finest_step(acquisition, field_window: str = "full", calibrate_sources: bool = True):
    """``Reconstructor._step`` of ``acquisition``'s finest stage as the solver runs it there (TV on, the default
    validation split, the sources' positions trained when ``calibrate_sources``;
    :func:`benchmarks.step_profile_cpu.finest_stage_step`), after one warm-up step."""
    from benchmarks.step_profile_cpu import finest_stage_step

    step = finest_stage_step(acquisition, field_window=field_window, calibrate_sources=calibrate_sources,
                             calibration_from_stage=0)[0]
    step()
    return step


def main() -> None:
    from napari_fdt.data.io import read_acquisition

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--acquisition", default=str(ROOT / "sample_data" / "letters"), help="default: the bundled sample")
    ap.add_argument("--field-window", default="full", choices=["full", "split"], help="full: the window CUDA runs")
    ap.add_argument("--steps", type=int, default=20)
    args = ap.parse_args()
    counter = count_syncs(finest_step(read_acquisition(args.acquisition), args.field_window), args.steps)
    print(f"{counter.total / args.steps:.2f} host waits per iteration ({args.steps} iterations, field window "
          f"{args.field_window}):")
    for (name, site), n in counter.sites.most_common():
        print(f"  {n / args.steps:5.2f}  {name:22s} {site}")


if __name__ == "__main__":
    main()
