"""Plots of ``benchmarks/suite.py`` results: error against wall time, per scene.

    python -m benchmarks run plot_suite benchmarks/results/suite_cuda.json [more.json ...] [--out docs/images]

Writes ``suite_<device>_<scene>.png`` (relative Δn error and normalised PSNR/SSIM against seconds, stage
boundaries marked, the authors' quoted 500-iteration accuracy drawn for the demo scene). Needs matplotlib.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

#: The authors' code on the demo (issue 5; quoted, not measured here): normalised PSNR/SSIM after 500 iterations, ~12 min on one H100.
AUTHORS_500 = {"psnr": 24.0, "ssim": 0.59, "seconds": 12 * 60}


def plot(result: dict, device_name: str, out_dir: Path, tag: str) -> list[Path]:
    paths = []
    for sc in result["scenes"]:
        c = sc["curve"]
        if not c:
            continue
        t = [p["wall_s"] for p in c]
        fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
        axes[0].plot(t, [p["relative_delta_n_error"] for p in c], "-o", ms=3)
        axes[0].set_ylabel("relative Δn error")
        axes[1].plot(t, [p["paper_psnr"] for p in c], "-o", ms=3)
        axes[1].set_ylabel("normalised PSNR (dB)")
        axes[2].plot(t, [p["paper_ssim"] for p in c], "-o", ms=3)
        axes[2].set_ylabel("normalised SSIM")
        if sc["scene"] == "demo":
            axes[1].axhline(AUTHORS_500["psnr"], color="r", ls="--", label="authors' code, 500 it (≈12 min, quoted)")
            axes[2].axhline(AUTHORS_500["ssim"], color="r", ls="--", label="authors' code, 500 it (≈12 min, quoted)")
            axes[1].legend(fontsize=7, loc="lower right")
        for ax in axes:
            ax.set_xlabel("wall time (s)")
            ax.grid(alpha=0.3)
            for p in c:
                if p["stage_complete"]:
                    ax.axvline(p["wall_s"], color="0.7", lw=0.8)
        fig.suptitle(f"{sc['scene']}: {sc['image'][0]}×{sc['image'][1]}×{sc['n_slices']}, {sc['n_images']} images — {device_name}", fontsize=10)
        fig.tight_layout()
        path = out_dir / f"suite_{tag}_{sc['scene']}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("results", nargs="+", type=Path)
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "images")
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for f in args.results:
        res = json.loads(f.read_text())
        tag = res["hardware"]["device"].split(":")[0]
        for path in plot(res, res["hardware"]["name"], args.out, tag):
            print(f"wrote {path}")


if __name__ == "__main__":
    main()
