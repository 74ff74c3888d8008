"""Settings on the authors' demo geometry (issue 5): which solver settings reach which accuracy how fast.

    python -m benchmarks run demo_variants --device cuda [--variants default,tv,...] [--iterations 200,200,400]

Simulates the demo scene of ``benchmarks/suite.py`` once, then runs each variant (a dict of
``SolverConfig`` overrides) with the same data and seed, printing relative Δn error, the authors'
normalised PSNR/SSIM and Δn statistics every 100 iterations. Writes
``benchmarks/results/demo_variants_<device>.json``; ``--save-volumes DIR`` also stores each final Δn (float16 .npy).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from benchmarks._results import results_file, write_document  # noqa: E402
from benchmarks.suite import _letters_scene, run_scene  # noqa: E402
from napari_fdt import resolve_device  # noqa: E402
from napari_fdt.recon.settings.config import SolverConfig, StageConfig  # noqa: E402

VARIANTS = {
    "default": {},
    "tvxy": {"tv_xy_weight": 50.0},
    "tv_strong_ms": {"tv_xy_weight": 50.0, "tv_z_weight": 25.0, "coarse_model": "multislice"},
    "tv_strong_bigbatch": {"tv_xy_weight": 50.0, "tv_z_weight": 25.0, "_batches": [120, 60, None]},
    "tvxy200": {"tv_xy_weight": 200.0, "tv_z_weight": 25.0},
    "tv": {"tv_xy_weight": 10.0, "tv_z_weight": 5.0},
    "tv_strong": {"tv_xy_weight": 50.0, "tv_z_weight": 25.0},
    "dnmax05": {"delta_n_max": 0.05},
    "lr02": {"lr_ri": 0.02},
    "multislice_coarse": {"coarse_model": "multislice"},
    "signed": {"activation": "signed"},
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="auto")
    p.add_argument("--variants", default="default,tv,tv_strong,dnmax05,lr02")
    p.add_argument("--iterations", default="200,200,400")
    p.add_argument("--extra", default="{}", help="JSON dict of extra variants")
    p.add_argument("--save-volumes", type=Path, default=None)
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--best-config", type=Path, default=None,
                   help="write the configuration of the variant that first reached the authors' 500-iteration accuracy "
                        "(else the one with the best final PSNR) here")
    a = p.parse_args()
    device = resolve_device(a.device)
    variants = dict(VARIANTS, **json.loads(a.extra))
    its = [int(v) for v in a.iterations.split(",")]
    t = time.perf_counter()
    acq, truth = _letters_scene(512, 14, 39, 84.0, 100, device, text="UCDAVIS")
    print(f"demo data in {time.perf_counter() - t:.1f} s", flush=True)
    results = {"runs": []}
    for name in a.variants.split(","):
        over = dict(variants[name])
        batches = over.pop("_batches", [None, None, None])
        cfg = SolverConfig(stages=[StageConfig(f, n, b) for f, n, b in zip((4, 2, 1), its, batches)], batch_size=30,
                           snapshot_every=25, **over)
        res = run_scene(f"demo/{name}", acq, truth, cfg, device, eval_every=100)
        res["variant"] = name
        results["runs"].append(res)
        f = res["final"]
        print(f"== {name}: {res['wall_s']:.1f} s  rel {f['relative_delta_n_error']:.3f}  PSNR {f['paper_psnr']:.2f}  SSIM {f['paper_ssim']:.3f}", flush=True)
        if a.save_volumes is not None:
            a.save_volumes.mkdir(parents=True, exist_ok=True)
            np.save(a.save_volumes / f"{name}.npy", res.pop("_delta_n").astype(np.float16))
        res.pop("_delta_n", None)
    if a.best_config is not None:
        def first_hit(r):
            hits = [c["wall_s"] for c in r["curve"] if c["paper_psnr"] >= 24.0 and c["paper_ssim"] >= 0.59]
            return min(hits) if hits else float("inf")
        best = min(results["runs"], key=lambda r: (first_hit(r), -r["final"]["paper_psnr"]))
        a.best_config.write_text(json.dumps(best["config"], indent=1))
        print(f"best variant: {best['variant']} (first at PSNR >= 24 and SSIM >= 0.59 after {first_hit(best):.1f} s)")
    out = write_document(a.out or results_file("demo_variants", device, table=False), results, device)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
