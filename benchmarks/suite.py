"""Speed against error: the benchmark suite. One command records, for standard scenes, the error
against wall time (relative Δn error, the authors' normalised PSNR/SSIM, image loss), seconds per
iteration per stage and peak memory::

    python -m benchmarks run suite --device cuda                       # sample, demo, big
    python -m benchmarks run suite --device cpu --scenes sample        # the CPU-sized scene only
    python -m benchmarks run plot_suite benchmarks/results/suite_cuda.json   # PNG plots into docs/images/

Scenes
- ``sample``: the bundled ``sample_data/letters`` (96², 8 slices, 64 sources), default settings.
- ``demo``: the authors' demo geometry: 512² pixels of 0.33 µm, 14 slices 1.5 µm apart, letters 100 px
  tall on the even slices at Δn 0.03 over n_b 1.33, λ 0.6 µm, NA 0.65, a regular 39×39 grid of sources
  (1521) spanning ±42 µm, 50 µm below the volume, initial positions jittered by 1 µm, camera focused on
  the middle of the volume.
- ``big``: 1024² × 24 slices, 19×19 = 361 sources spanning ±84 µm, 50 µm deep, letters 200 px tall.

Wall time counts everything the user waits for once the data is loaded (solver set-up, gain
initialisation, every iteration, snapshots), and excludes the suite's own metric evaluations (done
between iterations while the solver's generator is paused). Writes ``benchmarks/results/suite_<device>.json``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks._results import results_file, write_document
from napari_fdt import Optics, read_acquisition, read_volume_tiff, resolve_device, source_grid
from napari_fdt.recon.assess.metrics import paper_normalised_metrics, relative_delta_n_error
from napari_fdt.recon.run.solver import Reconstructor
from napari_fdt.recon.settings.config import SolverConfig, StageConfig
from napari_fdt.sim.simulate import make_scene, simulate

ROOT = Path(__file__).resolve().parents[1]


def scene_sample(device):
    acq = read_acquisition(ROOT / "sample_data" / "letters")
    truth = read_volume_tiff(ROOT / "sample_data" / "letters" / "ground_truth_ri.tif")[0] - acq.optics.n_background
    return acq, truth, SolverConfig()


def _letters_scene(side, n_slices, n_grid, span_um, letter_px, device, text="FDT"):
    o = Optics(wavelength_um=0.6, n_background=1.33, na=0.65, pixel_size_um=0.33, n_slices=n_slices,
               slice_spacing_um=1.5, image_plane_um=0.5 * n_slices * 1.5)
    dn = make_scene("letters", (side, side), o, delta_n=0.03, text=text, letter_height_px=letter_px)
    src = source_grid(n_grid, span_um, 50.0)
    sim = simulate(dn, o, src, device=str(device), seed=0, batch_size=32)
    return sim.acquisition, dn


def demo_config(iterations=(150, 150, 700)) -> SolverConfig:
    """Settings for the demo scene: lateral TV (without it the unconstrained background grows: relative Δn
    error 3.9 against 0.86 with it, ``benchmarks/demo_variants.py``), batch 30 as the authors."""
    return SolverConfig(stages=[StageConfig(4, iterations[0]), StageConfig(2, iterations[1]), StageConfig(1, iterations[2])],
                        batch_size=30, snapshot_every=25, tv_xy_weight=50.0, tv_z_weight=25.0)


def scene_demo(device, iterations=(150, 150, 700), config: SolverConfig | None = None):
    acq, dn = _letters_scene(512, 14, 39, 84.0, 100, device, text="UCDAVIS")
    return acq, dn, config or demo_config(iterations)


def scene_big(device, iterations=(150, 150, 300), config: SolverConfig | None = None):
    acq, dn = _letters_scene(1024, 24, 19, 168.0, 200, device, text="FDT")
    if config is None:
        config = demo_config(iterations)
    else:  # the demo's settings with this scene's iterations
        config = SolverConfig.from_dict(dict(config.to_dict(), stages=[dict(s, iterations=n) for s, n in zip(config.to_dict()["stages"], iterations)]))
    return acq, dn, config


def run_scene(name, acq, truth, cfg, device, eval_every):
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
    t_solver = 0.0
    t0 = time.perf_counter()
    rec = Reconstructor(acq, cfg, device=device)
    gen = rec.run()
    t_solver += time.perf_counter() - t0
    curve = []
    last_eval = -10**9
    while True:
        t1 = time.perf_counter()
        try:
            snap = next(gen)
        except StopIteration:
            t_solver += time.perf_counter() - t1
            break
        t_solver += time.perf_counter() - t1
        if snap.phase == "tv_choice":  # the TV choice (its time counts; its volumes are not the run's)
            continue
        if snap.stage_complete or snap.global_iteration - last_eval >= eval_every:
            last_eval = snap.global_iteration
            pred = snap.delta_n_full()
            pm = paper_normalised_metrics(pred, truth)
            curve.append({"wall_s": t_solver, "stage": snap.stage, "factor": snap.factor, "iteration": snap.global_iteration,
                          "relative_delta_n_error": relative_delta_n_error(pred, truth),
                          "delta_n_mean": float(pred.mean()), "delta_n_max": float(pred.max()),
                          "delta_n_p999": float(np.quantile(pred, 0.999)),
                          "slice_means": [float(v) for v in pred.mean(axis=(1, 2))],
                          "paper_psnr": pm["psnr"], "paper_ssim": pm["ssim"],
                          "loss": sum(v for k, v in snap.losses.items() if k in ("l1", "l2")),
                          "losses": snap.losses, "stage_complete": snap.stage_complete})
            c = curve[-1]
            print(f"  {name}: {c['wall_s']:7.2f} s  stage {c['stage']} it {c['iteration']:5d}  rel err {c['relative_delta_n_error']:.3f}  "
                  f"PSNR {c['paper_psnr']:.2f}  SSIM {c['paper_ssim']:.3f}  Δn mean {c['delta_n_mean']:.5f} p99.9 {c['delta_n_p999']:.4f} "
                  f"max {c['delta_n_max']:.4f}", flush=True)
    peak = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None
    return {
        "scene": name, "image": list(acq.image_shape), "n_slices": acq.optics.n_slices, "n_images": acq.n_images,
        "config": cfg.to_dict(), "wall_s": t_solver, "peak_memory_gib": peak,
        "stages": [r.to_dict() for r in rec.stages],
        "curve": curve,
        "final": curve[-1] if curve else None,
        "_delta_n": pred,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="auto")
    p.add_argument("--scenes", default="sample,demo,big")
    p.add_argument("--eval-every", type=int, default=50, help="iterations between metric evaluations")
    p.add_argument("--demo-iterations", default="150,150,700")
    p.add_argument("--demo-config", type=Path, default=None, help="JSON configuration for the demo and big scenes")
    p.add_argument("--big-iterations", default="150,150,300")
    p.add_argument("--coarse-model", default=None, help="override coarse_model in every scene's configuration (issue 16)")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()
    device = resolve_device(args.device)
    out = {"scenes": []}
    path = args.out or results_file("suite", device, table=False)
    demo_cfg = None
    if args.demo_config is not None:
        from napari_fdt.recon.settings.config import load_config
        demo_cfg = load_config(args.demo_config)
    for name in args.scenes.split(","):
        t = time.perf_counter()
        if name == "sample":
            acq, truth, cfg = scene_sample(device)
        elif name == "demo":
            acq, truth, cfg = scene_demo(device, tuple(int(v) for v in args.demo_iterations.split(",")), demo_cfg)
        elif name == "big":
            acq, truth, cfg = scene_big(device, tuple(int(v) for v in args.big_iterations.split(",")), demo_cfg)
        else:
            raise SystemExit(f"unknown scene {name}")
        if args.coarse_model is not None:
            from napari_fdt.recon.settings.config import SolverConfig
            cfg = SolverConfig.from_dict(dict(cfg.to_dict(), coarse_model=args.coarse_model))
        print(f"{name}: data ready in {time.perf_counter() - t:.1f} s ({acq.n_images} images {acq.image_shape}, {acq.optics.n_slices} slices)", flush=True)
        res = run_scene(name, acq, truth, cfg, device, args.eval_every)
        res.pop("_delta_n", None)
        out["scenes"].append(res)
        write_document(path, out, device)  # after every scene: a cut-off run keeps what it did
        f = res["final"]
        print(f"{name}: {res['wall_s']:.1f} s, rel err {f['relative_delta_n_error']:.3f}, PSNR {f['paper_psnr']:.2f}, "
              f"SSIM {f['paper_ssim']:.3f}, peak {res['peak_memory_gib']} GiB; s/it per stage "
              + ", ".join(f"{s['factor']}: {s['seconds_per_iteration'] * 1e3:.1f} ms" for s in res["stages"]), flush=True)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
