"""``python -m napari_fdt`` that records which files under a folder this process writes (for test_distributed.py).

Run it in place of ``-m napari_fdt`` (e.g. as torchrun's script). Python audit hooks see every ``open`` for
writing (tifffile, JSON, temporary files), every rename (the atomic replace of each output and checkpoint)
and every mkdir; those whose path lies under ``$FDT_AUDIT_WATCH`` are written, one per line, to
``$FDT_AUDIT_DIR/rank$RANK.txt`` when the process exits; the number of images this rank took of each batch
goes to ``rank$RANK_batches.txt``.

``FDT_TEST_FAIL=R:K`` makes rank R raise at its K-th prediction (a rank failing mid-run).
"""

import atexit
import os
import runpy
import sys

WATCH = os.path.realpath(os.environ["FDT_AUDIT_WATCH"])
LOG = os.path.join(os.environ["FDT_AUDIT_DIR"], f"rank{os.environ.get('RANK', 'none')}.txt")
WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_APPEND | os.O_TRUNC
seen: list[str] = []
local_sizes: list[int] = []


def _under_watch(path) -> str | None:
    if isinstance(path, int):
        return None
    try:
        real = os.path.realpath(os.fsdecode(path))
    except (TypeError, ValueError):
        return None
    return real if real == WATCH or real.startswith(WATCH + os.sep) else None


def _hook(event: str, args: tuple) -> None:
    if event == "open":
        path, mode, flags = args
        writing = (isinstance(mode, str) and any(c in mode for c in "wax+")) or (isinstance(flags, int) and flags & WRITE_FLAGS)
        paths = [path] if writing else []
    elif event == "os.rename":
        paths = [args[1]]
    elif event in ("os.mkdir", "os.remove", "os.truncate"):
        paths = [args[0]]
    else:
        return
    for p in paths:
        real = _under_watch(p)
        if real is not None:
            seen.append(f"{event} {real}")


def _write_log() -> None:
    with open(LOG, "w", encoding="utf-8") as fh:
        fh.write("".join(line + "\n" for line in seen))
    with open(LOG.replace(".txt", "_batches.txt"), "w", encoding="utf-8") as fh:
        fh.write(" ".join(map(str, local_sizes)))


def _count_local_batches() -> None:
    from napari_fdt.recon.problem.distributed import Group

    local = Group.local

    def counted(self, indices):
        out = local(self, indices)
        local_sizes.append(len(out))
        return out

    Group.local = counted


def _fail_on_request() -> None:
    rank, _, call = os.environ.get("FDT_TEST_FAIL", "").partition(":")
    if not call or os.environ.get("RANK") != rank:
        return
    from napari_fdt.recon.run.solver import Reconstructor

    predict, calls = Reconstructor._predict_normalised, [0]

    def failing(self, *args):
        calls[0] += 1
        if calls[0] == int(call):
            raise RuntimeError(f"injected failure on rank {rank}")
        return predict(self, *args)

    Reconstructor._predict_normalised = failing


_fail_on_request()
_count_local_batches()
atexit.register(_write_log)
sys.addaudithook(_hook)
sys.argv = ["napari_fdt", *sys.argv[1:]]
runpy.run_module("napari_fdt", run_name="__main__", alter_sys=True)
