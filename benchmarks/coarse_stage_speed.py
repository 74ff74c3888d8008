"""Cost of one training iteration per coarse-to-fine stage, and the operations it launches (issue 16, item 1).

    OMP_NUM_THREADS=1 python -m benchmarks run coarse_stage_speed --device cpu            # sample + demo geometry
    python -m benchmarks run coarse_stage_speed --device cuda --cuda-graph                # adds CUDA-graph rows

For each geometry and stage factor (4, 2, 1) the stage is built as the solver builds it
(:func:`napari_fdt.recon.problem.stages.build_stage`) and one iteration is timed: forward through the stage model, an L2
loss against the stage's images, backward to Δn (stage grid), the source positions and the gains. Models:

- ``envelope``: :class:`~napari_fdt.model.envelope.EnvelopeModel`, all sources and slices batched (``images_batched``,
  its path on CUDA);
- ``envelope_per_slice``: the same model one slice at a time (``images_per_slice``, its path on the CPU);
- ``multislice``: :class:`~napari_fdt.model.forward.MultiSliceModel` on the field grid the pupil needs;
- ``envelope_graph`` (``--cuda-graph``, CUDA only): the batched envelope captured in CUDA graphs
  (:mod:`benchmarks._graphed`).

``ops`` counts the operations of one iteration that run arithmetic (torch.profiler, CPU activity: leaf ATen
operations other than views and allocations, each FFT once): on a GPU each is at least one kernel launch, so it
is the launch-bound proxy. Times are medians of ``--repeats`` iterations after
two warm-up ones. The demo geometry (512², 14 slices, NA 0.65, 1521 sources, batch 30) uses random images of
the right shape: only the timing matters here. Writes ``benchmarks/results/coarse_stage_<device>.json``.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks._results import results_file, write_document
from napari_fdt import Optics, read_acquisition, resolve_device, source_grid
from napari_fdt.recon.problem.stages import build_stage

ROOT = Path(__file__).resolve().parents[1]


def geometry(name: str):
    """(optics, normalised images (N, H, W), sources (N, 3) µm, batch size)."""
    if name == "sample":
        acq = read_acquisition(ROOT / "sample_data" / "letters")
        imgs = torch.as_tensor(np.asarray(acq.images, dtype=np.float32))
        return acq.optics, imgs / imgs.mean(), np.asarray(acq.sources_um), 16
    if name == "demo":
        o = Optics(wavelength_um=0.6, n_background=1.33, na=0.65, pixel_size_um=0.33, n_slices=14,
                   slice_spacing_um=1.5, image_plane_um=10.5)
        src = source_grid(39, 84.0, 50.0)
        gen = torch.Generator().manual_seed(0)
        imgs = 1.0 + 0.1 * torch.rand(60, 512, 512, generator=gen)  # only the first batch is used
        return o, imgs, src[:60], 30
    raise ValueError(name)


#: ATen operations that only make views, allocate or dispatch: no arithmetic kernel of their own.
_NO_KERNEL = {"aten::as_strided", "aten::as_strided_", "aten::empty", "aten::empty_strided", "aten::empty_like", "aten::view",
              "aten::alias", "aten::resize_", "aten::result_type", "aten::_unsafe_view", "aten::_reshape_alias",
              "aten::view_as_real", "aten::view_as_complex", "aten::lift_fresh", "aten::detach", "aten::select", "aten::slice",
              "aten::unsqueeze", "aten::squeeze", "aten::expand", "aten::reshape", "aten::t", "aten::transpose", "aten::permute",
              "aten::_conj", "aten::conj", "aten::scalar_tensor", "aten::unbind", "aten::split"}


def _kernel_ops(fn) -> int:
    """Operations of ``fn`` that run arithmetic: leaf ATen operations minus views/allocations, an FFT counted once."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        fn()

    def inside_fft(e) -> bool:
        p = e.cpu_parent
        while p is not None:
            if p.name.startswith("aten::_fft_"):
                return True
            p = p.cpu_parent
        return False

    def scalar_copy(e) -> bool:
        # a Python number promoted to a 0-dim tensor: a copy on the CPU, a kernel argument on a GPU
        p = e.cpu_parent
        while p is not None and p.name in ("aten::_to_copy", "aten::to"):
            if all(len(s) == 0 for s in p.input_shapes if isinstance(s, list)):
                return True
            p = p.cpu_parent
        return False

    count = 0
    for e in prof.events():
        if not e.name.startswith("aten::") or inside_fft(e) or scalar_copy(e):
            continue
        if e.name.startswith("aten::_fft_"):
            count += 1
        elif e.name not in _NO_KERNEL and not any(c.name.startswith("aten::") for c in e.cpu_children):
            count += 1
    return count


def _sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_stage(stage, model_call, batch, device, repeats):
    """(median seconds, ops) of one forward + backward of the stage."""
    g_h, g_w = stage.grid_shape
    n = stage.optics.n_slices
    gen = torch.Generator().manual_seed(1)
    dn = (0.01 * torch.rand(n, g_h, g_w, generator=gen)).to(device).requires_grad_()
    src0 = stage.stage_sources(torch.as_tensor(SOURCES[: batch], dtype=torch.float32)).to(device)
    src = src0.clone().requires_grad_()
    gain = torch.ones(batch, device=device, requires_grad=True)
    target = stage.images[:batch].to(device)
    call = model_call(dn, src, gain)

    def step():
        pred = call(dn, src, gain)
        loss = (pred - target).square().mean()
        loss.backward()
        dn.grad = src.grad = gain.grad = None

    for _ in range(2):
        step()
    _sync(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        step()
        _sync(device)
        times.append(time.perf_counter() - t0)
    ops = _kernel_ops(step)
    return statistics.median(times), ops


SOURCES: np.ndarray = np.zeros((0, 3))


def main() -> None:
    global SOURCES
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--geometries", default="sample,demo")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--cuda-graph", action="store_true")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()
    device = resolve_device(args.device)
    rows = []
    for geo in args.geometries.split(","):
        optics, imgs, src, batch = geometry(geo)
        SOURCES = np.asarray(src, dtype=np.float64)
        for factor in (4, 2, 1):
            models = ["multislice"] if factor == 1 else ["envelope", "envelope_per_slice", "multislice"]
            if args.cuda_graph and factor > 1 and device.type == "cuda":
                models.append("envelope_graph")
            for name in models:
                coarse = "multislice" if name == "multislice" else "envelope"
                stage = build_stage(0, factor, 1, optics, imgs, SOURCES, device=device, coarse_model=coarse)
                if name == "multislice":
                    def call_for(dn, s, g, stage=stage):
                        return lambda d, s_, g_: stage.model(stage.to_field_grid(d), s_, g_)
                elif name == "envelope_per_slice":
                    def call_for(dn, s, g, stage=stage):
                        return stage.model.images_per_slice
                elif name == "envelope_graph":
                    def call_for(dn, s, g, stage=stage):
                        from benchmarks._graphed import graphed_model

                        return graphed_model(stage.model, dn, s, g)
                else:
                    def call_for(dn, s, g, stage=stage):
                        return stage.model.images_batched
                sec, ops = time_stage(stage, call_for, batch, device, args.repeats)
                row = {"geometry": geo, "factor": factor, "model": name, "field_grid": list(stage.image_shape),
                       "window": list(stage.window), "batch": batch, "n_slices": optics.n_slices,
                       "ms_per_iteration": 1e3 * sec, "ops_per_iteration": ops}
                rows.append(row)
                print(f"{geo:7s} ×{factor} {name:19s} field {stage.image_shape} window {stage.window}: "
                      f"{1e3 * sec:8.1f} ms/it, {ops:5d} ops", flush=True)
    out = write_document(args.out or results_file("coarse_stage", device, table=False), {"rows": rows}, device)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
