"""Forward-model throughput: image-slices per second, forward only and forward + backward.

Usage (from the repository root, with napari-fdt installed)::

    python -m benchmarks run forward_throughput --device cpu            # 256² and 512² scenes
    python -m benchmarks run forward_throughput --device cuda --gpu     # 512²×14 and 1024²×24, batch 30

Writes ``benchmarks/results/forward_<device>.json`` (hardware, versions, per-scene timings) and prints
a Markdown table for ``docs/benchmarks.md``. Timing only: the numbers are never asserted anywhere.
Geometry of every scene: λ 0.6 µm, n_b 1.33, NA 0.65, pixel 0.33 µm, slices 1.5 µm apart (the paper's
demo), sources on a grid over 50 % of the field of view, 50 µm below the volume; the window is the one
the geometry needs (``napari_fdt.physics.grid.plan_grid``), reported beside the image size.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks._results import results_file, write_document
from napari_fdt import MultiSliceModel, Optics, plan_for_sources, resolve_device, source_grid

CPU_SCENES = [(256, 14, 8), (512, 14, 8)]
GPU_SCENES = [(512, 14, 30), (1024, 24, 30)]


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def bench_scene(side: int, n_slices: int, batch: int, device: torch.device, repeats: int) -> dict:
    optics = Optics(wavelength_um=0.6, n_background=1.33, na=0.65, pixel_size_um=0.33, n_slices=n_slices,
                    slice_spacing_um=1.5, image_plane_um=0.0)
    fov = side * optics.pixel_size_um
    n_side = max(2, int(np.sqrt(batch)))
    sources = source_grid(n_side, 0.5 * fov, 50.0)[:batch]
    sources = np.concatenate([sources] * (batch // len(sources) + 1))[:batch]
    plan = plan_for_sources(optics, (side, side), sources, warn=False)
    model = MultiSliceModel(optics, plan, device=device)
    gen = torch.Generator().manual_seed(0)
    dn = (0.02 * torch.rand(n_slices, side, side, generator=gen)).to(device)
    src = torch.tensor(sources, dtype=torch.float32, device=device)
    gain = torch.ones(batch, device=device)
    dn_pad = model.pad_volume(dn)

    def forward_only() -> None:
        with torch.no_grad():
            model(dn_pad, src, gain)

    def forward_backward() -> None:
        x = dn_pad.detach().requires_grad_()
        model(x, src, gain).mean().backward()

    out = {"image": [side, side], "window": list(plan.padded_shape), "n_slices": n_slices, "batch": batch}
    for name, fn in (("forward", forward_only), ("forward_backward", forward_backward)):
        fn()  # warm-up (plans FFTs, allocator)
        _sync(device)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            _sync(device)
            times.append(time.perf_counter() - t0)
        med = statistics.median(times)
        out[name] = {
            "seconds_per_batch_median": med,
            "seconds_per_batch_all": times,
            "image_slices_per_second": batch * n_slices / med,
        }
        if device.type == "cuda":
            out[name]["peak_memory_gib"] = torch.cuda.max_memory_allocated(device) / 2**30
            torch.cuda.reset_peak_memory_stats(device)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="auto")
    parser.add_argument("--gpu", action="store_true", help="the GPU scenes (512²×14 and 1024²×24 at batch 30)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    device = resolve_device(args.device)
    scenes = GPU_SCENES if args.gpu else CPU_SCENES
    hardware = {"name": torch.cuda.get_device_name(device) if device.type == "cuda" else _cpu_name()}
    results = {"hardware": hardware, "scenes": [bench_scene(s, n, b, device, args.repeats) for s, n, b in scenes]}
    out = write_document(args.out or results_file("forward", device, table=False), results, device)
    hardware = json.loads(out.read_text())["hardware"]
    print(f"hardware: {hardware['name']} ({hardware['device']}, {hardware['threads']} threads, torch {hardware['torch']})")
    print("| image | window | slices | batch | forward: s/batch | image-slices/s | fwd+bwd: s/batch | image-slices/s |")
    print("|---|---|---|---|---|---|---|---|")
    for r in results["scenes"]:
        f, fb = r["forward"], r["forward_backward"]
        print(f"| {r['image'][0]}² | {r['window'][0]}² | {r['n_slices']} | {r['batch']} | {f['seconds_per_batch_median']:.3f} | "
              f"{f['image_slices_per_second']:.0f} | {fb['seconds_per_batch_median']:.3f} | {fb['image_slices_per_second']:.0f} |")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
