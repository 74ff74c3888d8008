"""The thin screen's error and what sub-slices buy, per scene: images with 1, 2 and 4 screens per slice against a
continuous slab (16 screens per slice), and what each costs (issue 27; docs/physics.md, "Sub-slices").

    python -m benchmarks run forward_accuracy [--scenes beads,letters,cells] [--write]
    python -m benchmarks run forward_accuracy --field-grid [--every 3] [--write]     # issue 27's target: the 2x field grid

Scenes: the suite's geometries (``fdt simulate``'s phantoms, 64² px, 8 slices of 2 µm, NA 0.8, λ 0.635 µm, a hard
pupil and pixel integration, 7×7 sources 30 µm deep; *letters* is the bundled sample's geometry at 96² px). Error: the
median over images of the relative L2 difference inside the central 75 % of the field, each image with its own
least-squares gain (as issue 27 measured it). Seconds: one forward pass of 16 images on the CPU (float32), best of 3.
``--write`` replaces the block between the ``sub-slices`` markers of docs/physics.md.
"""

from __future__ import annotations

import argparse
import re
import time
from pathlib import Path

import numpy as np
import torch

from napari_fdt import Optics
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.model.oversampled import OversampledModel
from napari_fdt.physics.grid import plan_for_sources
from napari_fdt.sim.simulate import make_scene, source_grid

DOC = Path(__file__).resolve().parent.parent / "docs" / "physics.md"
START, END = "<!-- sub-slices:start -->", "<!-- sub-slices:end -->"
GRID_START, GRID_END = "<!-- field-grid:start -->", "<!-- field-grid:end -->"


def scene(name: str):
    shape = (96, 96) if name == "letters" else (64, 64)
    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=8, slice_spacing_um=2.0,
               image_plane_um=0.0)
    dn = make_scene(name, shape, o, rng=0)
    src = source_grid(7, 0.8 * shape[0] * o.pixel_size_um, 30.0)
    return o, dn, src


def images(o, dn, src, n: int, dtype=torch.float64, oversampling: int = 1) -> tuple[np.ndarray, float]:
    """Images (hard pupil, pixel means) with ``n`` screens per slice, the field on the camera grid (``oversampling``
    1) or on a grid twice as fine (2), and the seconds of one float32 forward pass of 16 images."""
    cls = OversampledModel if oversampling == 2 else MultiSliceModel
    model = cls(o, plan_for_sources(o, dn.shape[1:], src, warn=False), device="cpu", dtype=dtype,
                pupil_edge=0.0, pixel_integration=True, sub_slices=n)
    x, s = torch.as_tensor(dn, dtype=dtype), torch.as_tensor(src, dtype=dtype)
    out = []
    with torch.no_grad():
        for i in range(0, len(src), 16):
            out.append(model(x, s[i:i + 16], torch.ones(len(s[i:i + 16]), dtype=dtype)).numpy())
        m32 = cls(o, plan_for_sources(o, dn.shape[1:], src, warn=False), device="cpu", dtype=torch.float32,
                  pupil_edge=0.0, pixel_integration=True, sub_slices=n)
        best = float("inf")
        for _ in range(3):
            t = time.perf_counter()
            m32(x.float(), s[:16].float(), torch.ones(16))
            best = min(best, time.perf_counter() - t)
    return np.concatenate(out), best


def median_error(pred: np.ndarray, ref: np.ndarray) -> float:
    """Median over images of ‖g·pred − ref‖/‖ref‖ in the central 75 % of the field, g the least-squares gain."""
    h, w = ref.shape[1:]
    my, mx = int(round(h / 8)), int(round(w / 8))
    p, r = pred[:, my:h - my, mx:w - mx], ref[:, my:h - my, mx:w - mx]
    errs = []
    for a, b in zip(p, r):
        g = float((a * b).sum() / (a * a).sum())
        errs.append(float(np.linalg.norm(g * a - b) / np.linalg.norm(b)))
    return float(np.median(errs))


def publish(lines: list[str], write: bool) -> None:
    """Print a table block (its first and last lines are its markers) and, with ``write``, replace it in docs/physics.md."""
    block = "\n".join(lines)
    print(block)
    if write:
        start, end = lines[0], lines[-1]
        text = DOC.read_text(encoding="utf-8")
        text = re.sub(re.escape(start) + ".*?" + re.escape(end), lambda _: block, text, flags=re.S)
        DOC.write_text(text, encoding="utf-8")


def field_grid(names: list[str], every: int, write: bool) -> None:
    """Issue 27's target: against the continuous slab on a field grid twice as fine (16 screens per slice, float64),
    the camera-grid model and the fine-grid model, each with 1 and 4 screens per slice (every ``every``-th source)."""
    rows = []
    for name in names:
        o, dn, src = scene(name)
        src = src[::every]
        slab, _ = images(o, dn, src, 16, oversampling=2)
        err, sec = {}, {}
        for grid in (1, 2):
            for n in (1, 4):
                pred, sec[grid, n] = images(o, dn, src, n, oversampling=grid)
                err[grid, n] = median_error(pred, slab)
        rows.append((name, float(np.abs(dn).max()), err, sec, len(src)))
        print(name, {k: f"{v:.4f}" for k, v in err.items()}, {k: f"{v:.2f} s" for k, v in sec.items()}, flush=True)
    lines = [GRID_START, "",
             f"Made by `python -m benchmarks run forward_accuracy --field-grid --write` ({time.strftime('%Y-%m-%d')}, 2 CPU "
             "cores, torch " + torch.__version__ + "): median image error (gain fitted per image, central 75 % of the field) "
             "against the continuous slab on a field grid twice as fine as the camera's (16 screens per slice, float64; "
             "a hard pupil and pixel means, as `fdt simulate --pupil-edge 0 --pixel-integration true`), and one forward "
             "pass of 16 images (float32, CPU). *high* is `--forward-accuracy high` (4 screens per slice, the 2× grid).",
             "",
             "| scene (max Δn, images) | camera grid, 1 screen (the solver's) | camera grid, 4 | 2× grid, 1 | 2× grid, 4 (high) "
             "| seconds: camera 1 / camera 4 / 2× 1 / high |",
             "|---|---|---|---|---|---|"]
    for name, peak, e, s, n_img in rows:
        lines.append(f"| {name} ({peak:.3f}, {n_img}) | {100 * e[1, 1]:.2f} % | {100 * e[1, 4]:.2f} % | {100 * e[2, 1]:.2f} % | "
                     f"{100 * e[2, 4]:.3f} % | {s[1, 1]:.2f} / {s[1, 4]:.2f} / {s[2, 1]:.2f} / {s[2, 4]:.2f} |")
    publish([*lines, "", GRID_END], write)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="beads,letters,cells")
    ap.add_argument("--write", action="store_true")
    ap.add_argument("--field-grid", action="store_true",
                    help="issue 27's target: the camera grid and the 2x field grid against the slab on the 2x grid")
    ap.add_argument("--every", type=int, default=3, help="with --field-grid: every n-th source (the slab is slow)")
    args = ap.parse_args()
    torch.set_num_threads(2)
    if args.field_grid:
        field_grid(args.scenes.split(","), args.every, args.write)
        return
    rows = []
    for name in args.scenes.split(","):
        o, dn, src = scene(name)
        slab, _ = images(o, dn, src, 16)
        seconds = {}
        errors = {}
        for n in (1, 2, 4):
            pred, seconds[n] = images(o, dn, src, n)
            errors[n] = median_error(pred, slab)
        empty, _ = images(o, np.zeros_like(dn), src, 1)
        signal = median_error(empty, slab)  # what the object does to the images, for scale
        rows.append((name, float(np.abs(dn).max()), errors, seconds, signal))
        print(name, {n: f"{e:.4f}" for n, e in errors.items()}, {n: f"{s:.3f} s" for n, s in seconds.items()}, flush=True)
    lines = [START, "",
             f"Made by `python -m benchmarks run forward_accuracy --write` ({time.strftime('%Y-%m-%d')}, 2 CPU cores, "
             "torch " + torch.__version__ + "): median image error against the continuous slab (16 screens per slice; "
             "gain fitted per image, central 75 % of the field), and one forward pass of 16 images (float32, CPU).",
             "",
             "| scene (max Δn) | 1 screen per slice | 2 | 4 | seconds, 1 / 2 / 4 | the object's effect (homogeneous medium against the slab) |",
             "|---|---|---|---|---|---|"]
    for name, peak, e, s, signal in rows:
        lines.append(f"| {name} ({peak:.3f}) | {100 * e[1]:.2f} % | {100 * e[2]:.2f} % | {100 * e[4]:.3f} % | "
                     f"{s[1]:.2f} / {s[2]:.2f} / {s[4]:.2f} | {100 * signal:.0f} % |")
    publish([*lines, "", END], args.write)


if __name__ == "__main__":
    main()
