"""Numerical-stability sweep over hard geometries: forward model, gradient, short reconstruction.

Run from the repository root::

    python -m benchmarks run hard_cases            # writes docs/hard_cases.md

For each case it (a) runs the multi-slice forward model in float32 and float64 and reports the relative
L2 error of the float32 images against float64, (b) back-propagates a scalar loss to Δn and the source
positions in float32 and checks the gradients are finite, (c) where it makes sense runs a very short
reconstruction (two stages of 3 iterations) on a tiny noise-free simulated acquisition, and records the
:class:`~napari_fdt.errors.FDTWarning` messages the grid planning emits. Scenes are kept small (CPU).
``tests/test_hard_cases.py`` imports this module and asserts on the same measurements.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import traceback
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.errors import FDTInputError, FDTWarning
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.physics.grid import plan_for_sources
from napari_fdt.physics.optics import Optics
from napari_fdt.recon.run.solver import Reconstructor
from napari_fdt.recon.settings.config import SolverConfig, StageConfig
from napari_fdt.sim.simulate import simulate, source_grid

ROOT = Path(__file__).resolve().parents[1]
COMMAND = "python -m benchmarks run hard_cases"

#: Base optics of every case (overridden per case): 0.6 µm in water, NA 0.5, 0.5 µm pixels, 8 × 1 µm slices.
BASE = dict(wavelength_um=0.6, n_background=1.33, na=0.5, pixel_size_um=0.5, n_slices=8, slice_spacing_um=1.0,
            image_plane_um=0.0)


@dataclass
class Case:
    name: str
    description: str
    shape: tuple[int, int] = (32, 32)
    optics: dict = field(default_factory=dict)
    sources: np.ndarray | None = None  # (N, 3) µm; default a 2×2 grid spanning 6 µm, 20 µm deep
    scene: str = "bead"  # "bead" (one soft bead, Δn 0.02), "slab" (Δn over a block of slices) or "none"
    delta_n: float = 0.02
    slab_slices: tuple[int, int] | None = None
    reconstruct: bool = True
    images: str = "simulated"  # "simulated", "saturated", "one_zero", "zero", "zero_nosources"


def _default_sources() -> np.ndarray:
    return source_grid(2, 6.0, 20.0)


CASES: list[Case] = [
    Case("baseline", "reference geometry"),
    Case("deep_sources", "sources 300 µm deep (32×32 px of 0.5 µm, NA 0.5)",
         sources=source_grid(2, 6.0, 300.0)),
    Case("edge_sources", "sources at the image edge (x, y = ±8 µm of a 16 µm field)",
         sources=np.array([[8.0, 8.0, 20.0], [-8.0, 8.0, 20.0], [8.0, -8.0, 20.0], [-8.0, -8.0, 20.0]])),
    Case("outside_sources", "sources 4–12 µm outside the field (x = ±12, ±20 µm)",
         sources=np.array([[12.0, 0.0, 20.0], [-12.0, 0.0, 20.0], [0.0, 20.0, 20.0], [20.0, 20.0, 20.0]])),
    Case("high_contrast", "Δn 0.1 over 20 µm (20 slices of a 10 µm-wide block)",
         optics=dict(n_slices=20), scene="slab", delta_n=0.1, slab_slices=(0, 20)),
    Case("thick_volume", "64 slices of 1 µm", optics=dict(n_slices=64)),
    Case("oblique_slab", "Δn 0.02 through all 8 slices (a 10 µm block): the thin screens miss 1/cos θ − 1 of its phase "
         "for oblique light (6 % at this NA's edge ray; see Obliquity below)", scene="slab", slab_slices=(0, 8)),
    Case("odd_nonsquare", "37×50 grid", shape=(37, 50)),
    Case("fine_pixel", "pixel 0.2 µm < λ/(2·n_b) = 0.226 µm (evanescent band on the grid)",
         optics=dict(pixel_size_um=0.2), shape=(40, 40)),
    Case("image_plane_inside", "focal plane 4 µm below the top face (inside the 8 µm volume)",
         optics=dict(image_plane_um=4.0)),
    Case("single_image", "one image, one source", sources=np.array([[0.0, 0.0, 20.0]])),
    Case("saturated", "images clipped at 30 % of their maximum", images="saturated"),
    Case("one_zero_image", "image 1 of 4 all zero, sources given", images="one_zero"),
    Case("all_zero", "all-zero images, sources given", images="zero"),
    Case("all_zero_nosources", "all-zero images, no sources (solver must fit them)", images="zero_nosources"),
]


def make_delta_n(case: Case, optics: Optics) -> np.ndarray:
    n, (h, w) = optics.n_slices, case.shape
    dx = optics.pixel_size_um
    dn = np.zeros((n, h, w), np.float32)
    if case.scene == "none":
        return dn
    y = (np.arange(h) - h // 2) * dx
    x = (np.arange(w) - w // 2) * dx
    yy, xx = np.meshgrid(y, x, indexing="ij")
    if case.scene == "bead":
        z = (np.arange(n) - (n - 1) / 2) * optics.slice_spacing_um
        r_um = min(3.0, 0.4 * n * optics.slice_spacing_um)
        r = np.sqrt(z[:, None, None] ** 2 + yy[None] ** 2 + xx[None] ** 2)
        dn = case.delta_n / (1.0 + np.exp((r - r_um) / 0.3))
    elif case.scene == "slab":
        a, b = case.slab_slices
        inside = 0.5 * (1 - np.tanh((np.maximum(abs(yy), abs(xx)) - 5.0) / 0.3))  # 10 µm square, soft edge
        dn[a:b] = case.delta_n * inside
    return dn.astype(np.float32)


def window_error(optics: Optics, plan, dn: np.ndarray, src: np.ndarray, factor: float = 2.0) -> tuple[float, int]:
    """Relative L2 difference (float64) of the images on ``plan``'s window and on one ``factor`` times as wide."""
    import dataclasses

    from napari_fdt.physics.grid import next_fast_even

    h, w = plan.image_shape
    hp, wp = (next_fast_even(int(factor * s)) for s in plan.padded_shape)
    wide = dataclasses.replace(plan, padded_shape=(hp, wp), offset=(hp // 2 - h // 2, wp // 2 - w // 2))
    out = []
    for p in (plan, wide):
        m = MultiSliceModel(optics, p, device="cpu", dtype=torch.float64)
        with torch.no_grad():
            out.append(m(torch.from_numpy(dn).double(), torch.from_numpy(src).double()))
    return _rel_l2(out[0], out[1]), hp


def _rel_l2(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.linalg.vector_norm(a.double() - b.double()) / torch.linalg.vector_norm(b.double()))


def _finite(*xs) -> bool:
    return all(bool(torch.isfinite(torch.as_tensor(x)).all()) for x in xs)


def run_case(case: Case, *, reconstruct: bool = True, window_check: bool = False) -> dict:
    """Measure one case; returns a dict of results (never raises for the numerical part)."""
    t0 = time.perf_counter()
    optics = Optics(**{**BASE, **case.optics})
    src = _default_sources() if case.sources is None else np.asarray(case.sources, float)
    res: dict = dict(name=case.name, description=case.description, shape=case.shape, n_slices=optics.n_slices,
                     dx=optics.pixel_size_um, n_sources=len(src))
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        plan = plan_for_sources(optics, case.shape, src)
    res["warnings"] = [str(w.message) for w in rec if issubclass(w.category, FDTWarning)]
    res["window"] = plan.padded_shape
    dn = make_delta_n(case, optics)
    res["max_phase_rad"] = float(2 * math.pi * np.abs(dn).sum(0).max() * optics.slice_spacing_um / optics.wavelength_um)

    # (a) forward, float32 vs float64
    imgs = {}
    for dt in (torch.float32, torch.float64):
        m = MultiSliceModel(optics, plan, device="cpu", dtype=dt)
        with torch.no_grad():
            imgs[dt] = m(torch.from_numpy(dn).to(dt), torch.from_numpy(src).to(dt))
    res["forward_finite"] = _finite(imgs[torch.float32]) and _finite(imgs[torch.float64])
    res["f32_vs_f64"] = _rel_l2(imgs[torch.float32], imgs[torch.float64])
    res["image_max"] = float(imgs[torch.float64].max())
    # the planned window against one twice as wide (float64): what wrap-around costs
    res["window_error"], res["wide_window"] = window_error(optics, plan, dn, src) if window_check else (float("nan"), 0)

    # (b) gradient of a scalar loss in float32 w.r.t. Δn and the source positions
    m = MultiSliceModel(optics, plan, device="cpu", dtype=torch.float32)
    dn_t = torch.from_numpy(dn).clone().requires_grad_(True)
    src_t = torch.from_numpy(src).float().clone().requires_grad_(True)
    target = imgs[torch.float64].float() * 1.05
    pred = m(dn_t, src_t)
    loss = ((pred - target) ** 2).mean() / target.square().mean()
    loss.backward()
    res["grad_finite"] = _finite(loss.detach(), dn_t.grad, src_t.grad)
    res["grad_norm_dn"] = float(dn_t.grad.norm())
    res["grad_norm_src"] = float(src_t.grad.norm())

    # (c) very short reconstruction on a tiny noise-free simulated acquisition
    res["recon"] = "skipped"
    if reconstruct and case.reconstruct:
        res["recon"] = _reconstruct(case, optics, dn, src)
    res["seconds"] = time.perf_counter() - t0
    res["finite"] = res["forward_finite"] and res["grad_finite"] and not str(res["recon"]).startswith("NON-FINITE")
    return res


def _reconstruct(case: Case, optics: Optics, dn: np.ndarray, src: np.ndarray) -> str:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FDTWarning)
        sim = simulate(dn, optics, src, noise=False, brightness_spread=0.0, jitter_xy_um=0.3, jitter_depth_um=0.3,
                       device="cpu")
    acq = sim.acquisition
    sources = acq.sources_um
    if case.images == "saturated":
        imgs = np.minimum(acq.images, 0.3 * acq.images.max())
        acq = Acquisition(images=imgs.astype(np.float32), optics=optics, sources_um=sources)
    elif case.images == "one_zero":
        imgs = acq.images.copy()
        imgs[1] = 0
        acq = Acquisition(images=imgs, optics=optics, sources_um=sources)
    elif case.images in ("zero", "zero_nosources"):
        acq = Acquisition(images=np.zeros_like(acq.images), optics=optics,
                          sources_um=sources if case.images == "zero" else None)
    cfg = SolverConfig(stages=[StageConfig(2, 3), StageConfig(1, 3)], batch_size=4)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FDTWarning)
            rc = Reconstructor(acq, cfg, device="cpu")
            for _ in rc.run():
                pass
    except FDTInputError as exc:
        return f"FDTInputError: {exc}"
    except Exception as exc:  # a defect: report it, do not hide it
        tb = traceback.extract_tb(exc.__traceback__)[-1]
        return f"EXCEPTION {type(exc).__name__}: {exc} ({Path(tb.filename).name}:{tb.lineno})"
    vol = rc.delta_n_full()
    losses = list(rc.final_losses.values())
    if not (np.isfinite(vol).all() and np.isfinite(losses).all() and _finite(rc.calibration.sources.detach(), rc.calibration.log_gain.detach())):
        return "NON-FINITE result (NaN/Inf in volume, losses or calibration)"
    return (f"ok, loss {rc.final_losses.get('total', float('nan')):.3g}, "
            f"log-gain min {float(rc.calibration.log_gain.detach().min()):.3g}")


def markdown(results: list[dict], obliquity: list[dict] | None = None) -> str:
    lines = [
        "# Hard cases: numerical stability",
        "",
        f"Generated by `{COMMAND}` (CPU, {torch.__version__}).",
        "",
        "Base optics: λ 0.6 µm, n_b 1.33, NA 0.5, pixel 0.5 µm, 8 slices of 1 µm, focal plane at the top face; "
        "sources a 2×2 grid spanning 6 µm, 20 µm deep; Δn one soft bead (0.02, radius 3 µm) unless stated. "
        "Forward: images of all sources, float32 vs float64 (relative L2). Gradient: float32, loss "
        "‖I − 1.05·I₆₄‖²/‖1.05·I₆₄‖² w.r.t. Δn and source positions. Reconstruction: noise-free simulated "
        "acquisition, `SolverConfig(stages=[StageConfig(2, 3), StageConfig(1, 3)], batch_size=4)`, CPU. "
        "Window error: float64 images on the planned window against a window twice as wide (relative L2): what "
        "the periodic copies of the sources cost.",
        "",
        "| case | geometry | window | window error | warnings (FDTWarning) | finite | f32 vs f64 | grad finite | reconstruction | time (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        geom = f"{r['shape'][0]}×{r['shape'][1]} px of {r['dx']:g} µm, {r['n_slices']} slices, {r['n_sources']} src; {r['description']}"
        warn = "; ".join(w.split(":")[0] + (": evanescent" if "evanescent" in w else "") for w in r["warnings"]) or "none"
        rec = str(r["recon"]).replace("|", "/").replace("\n", " ")
        lines.append(
            f"| {r['name']} | {geom} | {r['window'][0]}×{r['window'][1]} | {r['window_error']:.1e} | {warn} | {'yes' if r['finite'] else 'NO'} | "
            f"{r['f32_vs_f64']:.1e} | {'yes' if r['grad_finite'] else 'NO'} | {rec} | {r['seconds']:.2f} |"
        )
    by = {r["name"]: r for r in results}
    lines += ["", "## Findings", ""]
    if "high_contrast" in by:
        lines.append(f"- high_contrast: the block's accumulated phase is {by['high_contrast']['max_phase_rad']:.1f} rad; "
                     "float32 stays at the float64 reference.")
    if "deep_sources" in by:
        lines.append(f"- deep_sources: the float32 error grows about linearly with source depth "
                     f"({by['deep_sources']['f32_vs_f64']:.1e} at 300 µm; a separate `run_case` sweep on a 16×16 image gave "
                     "3.0e-6 at 20, 8.4e-6 at 100, 1.8e-5 at 300 and 5.1e-5 at 600 µm): the propagation phase 2π·n_b·d/λ (≈ 4200 rad at 300 µm) is held in complex64. "
                     "Still far below shot noise at these depths; the solver itself always runs in float32.")
    worst = max(results, key=lambda r: r["window_error"] if r["window_error"] == r["window_error"] else -1.0)
    if worst["window_error"] == worst["window_error"]:
        lines.append(f"- Window error at most {worst['window_error']:.1e} ({worst['name']}). Before the pupil-tail term of "
                     "the window rule (docs/physics.md §4) the baseline's window was 64×64 and its images were 2.6 % off "
                     "a 6× wider window: the periodic copies' defocused discs ended 9 µm beyond the image, inside the "
                     "diffraction tails of the pupil's soft edge (they decay over λ/(2·0.03·NA) = 20 µm).")
    if "deep_sources" in by and by["deep_sources"]["window_error"] == by["deep_sources"]["window_error"]:
        lines.append(f"- deep_sources: nothing to warn about. The 384×384 window holds the sources' light "
                     f"(window error {by['deep_sources']['window_error']:.1e} with the Δn 0.02 bead, 1.2e-3 on a "
                     "homogeneous medium) and float32 costs only the error above; a strongly scattering sample "
                     "converges more slowly with the window (Δn 0.1 bead: 1.4 % at 384², 0.6 % at 480², 0.15 % at 768²), "
                     "within the shot noise of a 2000-photon image.")
    lines += [
        "- No hard case emits an FDTWarning except fine_pixel (evanescent band). Edge/outside sources, 300 µm depth, "
        "64 slices, an in-volume focal plane and Δn 0.1 are all silent: the planner sizes the window instead.",
        "- all_zero: `Reconstructor` raises `FDTInputError` (\"images: are all zero\") before any compute; without "
        "sources the source fit raises first, naming the blank images. No NaN.",
        "- saturated: clipped images reconstruct with finite values but **nothing detects or warns about saturation** "
        "(neither a float cap nor uint16 65535).",
        "- one_zero_image (and an outside source whose image is dark): with sources given, a blank image passes "
        "silently; its least-squares gain is clamped to 1e-6 (log-gain −13.8) and it stays in the loss. Without "
        "sources the source fit rejects the same data with FDTInputError (\"1 of 4 images are blank\"): inconsistent "
        "but finite.",
    ]
    if obliquity:
        lines += ["", "## Obliquity of the thin screen (`python -m benchmarks run obliquity`, docs/physics.md §6)", "",
                  "A uniform slab (Δn 0.02, T 8 µm) filling the window; the screens give every plane-wave component "
                  "2π·T·Δn/λ, the exact slab 2π·T·(sqrt((n_b+Δn)²/λ² − f²) − sqrt(n_b²/λ² − f²)). Image: a source 20 µm "
                  "below, the whole defocused disc, relative L2 after a least-squares gain.", "",
                  "| NA | phase error at the edge ray (any slice count) | image error | after refitting the depth | "
                  "with per-source 1/cos θ screens |", "|---|---|---|---|---|"]
        for r in obliquity:
            lines.append(f"| {r['na']:g} | {100 * r['error']:.1f} % | {100 * r['model']:.2f} % | "
                         f"{100 * r['model_refit']:.2f} % ({r['refit_depth_shift_um']:+.2f} µm) | {100 * r['ray_secant']:.2f} % |")
    lines += ["", "Full warning texts:", ""]
    for r in results:
        for w in r["warnings"]:
            lines.append(f"- {r['name']}: {w}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "hard_cases.md"))
    ap.add_argument("--no-reconstruct", action="store_true")
    ap.add_argument("--no-obliquity", action="store_true", help="skip the obliquity table (about 30 s)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    results = []
    for case in CASES:
        r = run_case(case, reconstruct=not args.no_reconstruct, window_check=True)
        print(f"{r['name']:22s} window {r['window']} finite {r['finite']} f32/f64 {r['f32_vs_f64']:.2e} "
              f"grad {r['grad_finite']} {r['seconds']:.2f}s warn {len(r['warnings'])} recon: {r['recon']}", flush=True)
        results.append(r)
    obliquity = []
    if not args.no_obliquity:
        from benchmarks import obliquity as ob

        for na in (0.45, 0.8):
            r = {**ob.measure_plane_wave(na, 8, 0.02), **ob.measure_image(na, 8, 0.02)}
            print(f"obliquity NA {na}: phase error {r['error']:.3f}, image {r['model']:.4f}", flush=True)
            obliquity.append(r)
    text = markdown(results, obliquity)
    out = Path(args.out)
    if out.exists():  # keep full_size_stack's block (it has its own command)
        old = out.read_text(encoding="utf-8")
        start, end = "<!-- full-size:start -->", "<!-- full-size:end -->"
        if start in old and end in old:
            text += "\n" + old[old.index(start): old.index(end) + len(end)] + "\n"
    out.write_text(text, encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
