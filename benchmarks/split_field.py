"""The split-field model against the full window: accuracy against a converged window, and one training step's time
(docs/decisions/split-field.md).

    python -m benchmarks run split_field [--scenes sample,beads,cells,cells_pupil,deep,letters128] [--device cuda] [--write]
    python -m benchmarks run split_field --scenes fibres_thick --volume RI.tif --sub-slices 2 --clearance-um 2,10

The second form measures the image error only, of the scene's geometry with another volume (a reconstruction: its RI
file, on the scene's grid), at the given sub-slices and clearances (µm beyond the light cone's margin).

Per scene (its truth volume, 8 of its sources for accuracy, 16 for timing): the relative image error (float64) of the
full-window model on the planned window and of :class:`~napari_fdt.model.split_field.SplitFieldModel` against the
full-window model on a window 1.8x the plan's (where the periodic copies are far: the converged answer of both), with
and without pixel integration; then one forward and backward pass (float32, a squared loss, gradients in the contrast
and the sources) of each, host clock, best of 3 after a warm-up. ``--write`` appends the rows to
``benchmarks/results/split_field_DEVICE.jsonl``. On CUDA the step is timed after a synchronise (and the full-window
model keeps its default backward mode there). Nothing is asserted; this reports.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
import warnings

import numpy as np
import torch

from benchmarks._results import append_row, results_file
from benchmarks.scenes import SCENES
from napari_fdt.data.io import read_acquisition, read_volume_tiff
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.model.split_field import SplitFieldModel
from napari_fdt.physics.grid import next_fast_even, plan_for_sources

DEFAULT_SCENES = "sample,beads,cells,cells_pupil,deep,letters128"


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.linalg.norm(a - b) / torch.linalg.norm(b))


def _step_s(model, dn: torch.Tensor, src: torch.Tensor, target: torch.Tensor, repeats: int = 3) -> float:
    def step():
        d = dn.clone().requires_grad_(True)
        s = src.clone().requires_grad_(True)
        (model(d, s) - target).square().mean().backward()
        if d.is_cuda:
            torch.cuda.synchronize()

    step()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        step()
        best = min(best, time.perf_counter() - t0)
    return best


def _geometry(name: str):
    """A registry scene's acquisition, its planned full window, the converged window (1.8x the plan's, where the
    periodic copies are far) and the plan's sources (N, 3) µm."""
    acq = read_acquisition(SCENES[name][0])
    all_src = np.asarray(acq.sources_um)
    plan = plan_for_sources(acq.optics, acq.image_shape, all_src, warn=False)
    n2 = next_fast_even(int(1.8 * max(plan.padded_shape)))
    (h, w) = plan.image_shape
    wide = dataclasses.replace(plan, padded_shape=(n2, n2), offset=(n2 // 2 - h // 2, n2 // 2 - w // 2))
    return acq, plan, wide, all_src


def _spread(all_src: np.ndarray, n: int, dtype: torch.dtype, device: str = "cpu") -> torch.Tensor:
    """``n`` sources spread over the list (first to last), as a tensor."""
    return torch.tensor(all_src[np.linspace(0, len(all_src) - 1, n).round().astype(int)], dtype=dtype, device=device)


def measure(name: str, device: str = "cpu") -> dict:
    acq, plan, wide, all_src = _geometry(name)
    o = acq.optics
    vol, _ = read_volume_tiff(SCENES[name][0] / "ground_truth_ri.tif")
    n2 = wide.padded_shape[0]
    row = {"scene": name, "image": list(acq.image_shape), "full_window": list(plan.padded_shape), "converged_window": n2}
    f64 = torch.float64
    dn = torch.tensor(vol - o.n_background, dtype=f64, device=device)
    src = _spread(all_src, 8, f64, device)
    with torch.no_grad():
        for pix in (False, True):
            tag = "_pixels" if pix else ""
            truth = MultiSliceModel(o, wide, device=device, dtype=f64, pixel_integration=pix)(dn, src)
            full = MultiSliceModel(o, plan, device=device, dtype=f64, pixel_integration=pix)
            split = SplitFieldModel(o, plan, device=device, dtype=f64, pixel_integration=pix)
            row[f"full_error{tag}"] = _rel(full(dn, src), truth)
            row[f"split_error{tag}"] = _rel(split(dn, src), truth)
            row["split_window"] = list(split.plan.padded_shape)
    f32 = torch.float32
    dn32 = dn.to(f32)
    src32 = _spread(all_src, 16, f32, device)
    for pix in (False, True):
        tag = "_pixels" if pix else ""
        full = MultiSliceModel(o, plan, device=device, dtype=f32, pixel_integration=pix)
        split = SplitFieldModel(o, plan, device=device, dtype=f32, pixel_integration=pix)
        with torch.no_grad():
            target = 1.05 * full(dn32, src32).roll(1, 0)
        row[f"full_step_s{tag}"] = _step_s(full, dn32, src32, target)
        row[f"split_step_s{tag}"] = _step_s(split, dn32, src32, target)
    return row


def volume_errors(name: str, volume: str, sub_slices: int, clearances: list[float]) -> dict:
    """Image errors (float64, 8 sources) of the planned full window and of the split window at each clearance against
    the full-window model on a window 1.8x the plan's, for ``volume`` (an RI file on the scene's grid)."""
    acq, plan, wide, all_src = _geometry(name)
    o = acq.optics
    f64 = torch.float64
    dn = torch.tensor(read_volume_tiff(volume)[0] - o.n_background, dtype=f64)
    src = _spread(all_src, 8, f64)
    with torch.no_grad():
        truth = MultiSliceModel(o, wide, device="cpu", dtype=f64, sub_slices=sub_slices)(dn, src)
        row = {"scene": name, "volume": volume, "sub_slices": sub_slices, "full_window": list(plan.padded_shape),
               "full_error": _rel(MultiSliceModel(o, plan, device="cpu", dtype=f64, sub_slices=sub_slices)(dn, src), truth)}
        for c in clearances:
            split = SplitFieldModel(o, plan, device="cpu", dtype=f64, sub_slices=sub_slices, clearance_um=c)
            row[f"split_error_{c:g}um"] = _rel(split(dn, src), truth)
            row[f"split_window_{c:g}um"] = list(split.plan.padded_shape)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=DEFAULT_SCENES, help=f"comma-separated registry names (default {DEFAULT_SCENES})")
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--write", action="store_true", help="append the rows to benchmarks/results/split_field_DEVICE.jsonl")
    ap.add_argument("--volume", help="an RI file on the scene's grid: the image errors for it instead (see above)")
    ap.add_argument("--sub-slices", type=int, default=1, help="screens per slice with --volume (default 1)")
    ap.add_argument("--clearance-um", default="2", help="comma-separated clearances with --volume, µm (default 2)")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    if args.volume:
        for name in args.scenes.split(","):
            print(volume_errors(name, args.volume, args.sub_slices, [float(c) for c in args.clearance_um.split(",")]))
        return
    print("| scene | image | full window | split window | image error: full / split | with pixel means | step (ms): full / split | with pixel means |")
    print("|---|---|---|---|---|---|---|---|")
    for name in args.scenes.split(","):
        row = measure(name, args.device)
        if args.write:
            append_row(results_file("split_field", args.device), row, args.device)
        print(f"| {name} | {row['image'][0]}² | {row['full_window'][0]}² | {row['split_window'][0]}² | "
              f"{100 * row['full_error']:.3f} % / {100 * row['split_error']:.3f} % | "
              f"{100 * row['full_error_pixels']:.3f} % / {100 * row['split_error_pixels']:.3f} % | "
              f"{1000 * row['full_step_s']:.0f} / {1000 * row['split_step_s']:.0f} | "
              f"{1000 * row['full_step_s_pixels']:.0f} / {1000 * row['split_step_s_pixels']:.0f} |", flush=True)


if __name__ == "__main__":
    main()
