"""Clean exits of distributed runs: N consecutive torchrun launches on CPU, each rank's exit status and any abort.

Question (issue 46, item 3): do ranks that finished leave without SIGABRT? A gloo rank once aborted at exit ("terminate
called without an active exception") after a run that had written its result; ``distributed.teardown`` now waits for
every rank at a barrier before the process group is destroyed. This launches the same short reconstruction
``--launches`` times in a row (default 20) with ``--ranks`` gloo ranks (default 2; torchrun's ``--standalone``) and
counts launches whose torchrun exit status is not 0, or whose output shows an abort, a ``terminate called`` or a signal.

    python -m benchmarks run distributed_exit [--launches 20] [--ranks 2] [--batch 4]

Prints one line per launch and a summary; exits 1 if any launch did not end cleanly. CPU only, about 10 s a launch.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BAD = ("terminate called", "SIGABRT", "Signal 6", "core dumped", "Aborted", "exitcode  : -")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--launches", type=int, default=20)
    ap.add_argument("--ranks", type=int, default=2)
    ap.add_argument("--batch", type=int, default=4)
    args = ap.parse_args()
    from benchmarks.scenes import tiny_scene
    from napari_fdt.data.io import write_acquisition
    from napari_fdt.recon.settings.config import SolverConfig, StageConfig

    work = Path(tempfile.mkdtemp(prefix="fdt_exit_"))
    acq = write_acquisition(tiny_scene(grid=4, seed=2).acquisition, work / "acq")
    SolverConfig(stages=[StageConfig(2, 4), StageConfig(1, 6)], batch_size=args.batch, final_stage_min_passes=0).save(work / "cfg.json")
    env = {k: v for k, v in os.environ.items() if k not in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")}
    env.update(OMP_NUM_THREADS="1", PYTHONPATH=os.pathsep.join([str(ROOT / "src"), env.get("PYTHONPATH", "")]))
    bad = 0
    for k in range(1, args.launches + 1):
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", str(args.ranks),
                               "-m", "napari_fdt", "reconstruct", str(acq), "--config", str(work / "cfg.json"), "--device", "cpu",
                               "--out", str(work / f"RI_{k}.tif"), "--quiet"], env=env, capture_output=True, text=True, timeout=600)
        text = proc.stdout + proc.stderr
        seen = [b for b in BAD if b in text]
        clean = proc.returncode == 0 and not seen and (work / f"RI_{k}.tif").is_file()
        bad += not clean
        print(f"launch {k:>2}: exit {proc.returncode}, {time.perf_counter() - t0:.1f} s, "
              f"{'clean' if clean else 'NOT CLEAN: ' + (', '.join(seen) or 'no output')}", flush=True)
        if not clean:
            print(text[-3000:], flush=True)
    print(f"{args.launches - bad} of {args.launches} launches ({args.ranks} ranks, batch {args.batch}) ended cleanly")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
