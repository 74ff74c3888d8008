"""Data-parallel scaling: the same reconstruction with 1 process and with N torchrun ranks.

Usage (from the repository root, with napari-fdt installed)::

    python -m benchmarks run distributed_scaling --device cpu --nproc 1 2                  # gloo on CPU
    python -m benchmarks run distributed_scaling --device cuda --nproc 1 2                 # one GPU per rank (NCCL)
    python -m benchmarks run distributed_scaling --device cuda --nproc 1 2 --backend gloo  # N ranks on one GPU

Each run is ``fdt reconstruct`` of ``--acquisition`` (default the bundled letters sample) with the default
configuration cut to ``--iterations`` per stage. It reports seconds per iteration of every stage (from the
report, which rank 0 writes), the wall time of the whole command (start-up, source fit and the final image
evaluation included), how far Δn and the sources are from the 1-process run, and the load imbalance of
the sharding: per batch, the most images any rank works on over the even share ``batch/N`` (ranks wait
for the slowest). On CPU, the threads (``--threads``, default all cores) are divided among the ranks.

Writes ``benchmarks/results/distributed_<device>.json`` and prints a Markdown table. Timing only: the
numbers are never asserted anywhere.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks._results import results_file, write_document

ROOT = Path(__file__).resolve().parents[1]


def imbalance(n_images: int, batch_size: int, world: int, iterations: int, seed: int) -> float:
    """Mean over batches of (most images on one rank) / (batch / world), for the solver's batch draws."""
    gen = torch.Generator().manual_seed(seed)
    order: list[int] = []
    b = min(batch_size, n_images)
    ratios = []
    for _ in range(iterations):
        while len(order) < b:
            order.extend(torch.randperm(n_images, generator=gen).tolist())
        batch, order = np.array(order[:b]), order[b:]
        ratios.append(max(int(np.sum(batch % world == r)) for r in range(world)) / (b / world))
    return float(np.mean(ratios))


def run(n: int, args, work: Path, cfg_path: Path, env_base: dict) -> dict:
    out = work / f"n{n}" / "RI.tif"
    env = dict(env_base)
    if args.device == "cpu":
        env["OMP_NUM_THREADS"] = str(max(1, args.threads // n))
    fdt = ["reconstruct", str(args.acquisition), "--out", str(out), "--config", str(cfg_path), "--device", args.device, "--quiet"]
    if n == 1:
        cmd = [sys.executable, "-m", "napari_fdt", *fdt]
    else:
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", str(n), "-m", "napari_fdt",
               *fdt, "--dist-backend", args.backend]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stdout}\n{proc.stderr}")
    report = json.loads(out.with_suffix(".json").read_text())
    import tifffile

    return {"processes": n, "wall_s": wall, "threads_per_process": env.get("OMP_NUM_THREADS"),
            "backend": report.get("distributed", {}).get("backend"), "device": report["device"],
            "stages": [{"factor": s["factor"], "seconds_per_iteration": s["seconds_per_iteration"]} for s in report["stages"]],
            "seconds_total": report["seconds_total"], "ri": tifffile.imread(out),
            "sources_um": np.array(report["calibration"]["sources_um"])}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default="cpu", help="cpu or cuda (each rank takes cuda:LOCAL_RANK)")
    p.add_argument("--nproc", type=int, nargs="+", default=[1, 2], help="process counts to compare (default 1 2)")
    p.add_argument("--backend", default="auto", choices=("auto", "nccl", "gloo"))
    p.add_argument("--acquisition", type=Path, default=ROOT / "sample_data" / "letters")
    p.add_argument("--iterations", type=int, default=20, help="iterations per stage of the default stages (default 20)")
    p.add_argument("--batch-size", type=int, default=None, help="override the default batch size (16)")
    p.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="CPU threads shared among the ranks")
    args = p.parse_args()

    from napari_fdt.data.io import read_acquisition
    from napari_fdt.recon.settings.config import SolverConfig

    cfg = SolverConfig()
    for s in cfg.stages:
        s.iterations = args.iterations
    if args.batch_size is not None:
        cfg.batch_size = args.batch_size
    n_images = read_acquisition(args.acquisition).n_images
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "src"), env.get("PYTHONPATH", "")])
    for name in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(name, None)
    results = []
    load_before = list(os.getloadavg())
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        cfg.save(work / "cfg.json")
        for n in args.nproc:
            r = run(n, args, work, work / "cfg.json", env)
            r["load_imbalance"] = imbalance(n_images, cfg.batch_size, n, cfg.total_iterations, cfg.seed)
            results.append(r)
    base = results[0]
    for r in results:
        r["max_abs_delta_ri_vs_first"] = float(np.abs(r["ri"] - base["ri"]).max())
        r["max_abs_delta_sources_um_vs_first"] = float(np.abs(r["sources_um"] - base["sources_um"]).max())
    for r in results:
        del r["ri"], r["sources_um"]
    hw = {"load_average_before_after": [load_before, list(os.getloadavg())]}  # other jobs on a shared machine
    acq = args.acquisition.resolve()
    acq_name = str(acq.relative_to(ROOT)) if acq.is_relative_to(ROOT) else str(acq)
    out = write_document(results_file("distributed", args.device, table=False),
                   {"hardware": hw, "acquisition": acq_name, "n_images": n_images, "batch_size": cfg.batch_size,
                    "iterations_per_stage": args.iterations, "runs": results}, args.device)
    print("| processes | backend | threads each | " + " | ".join(f"x{s['factor']} s/it" for s in base["stages"])
          + " | run s | wall s | load imbalance | max ΔRI vs first | max Δsources µm |")
    print("|" + "---|" * (7 + len(base["stages"])))
    for r in results:
        print(f"| {r['processes']} | {r['backend'] or '-'} | {r['threads_per_process'] or '-'} | "
              + " | ".join(f"{s['seconds_per_iteration']:.3f}" for s in r["stages"])
              + f" | {r['seconds_total']:.1f} | {r['wall_s']:.1f} | {r['load_imbalance']:.2f} | "
              f"{r['max_abs_delta_ri_vs_first']:.1e} | {r['max_abs_delta_sources_um_vs_first']:.1e} |")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
