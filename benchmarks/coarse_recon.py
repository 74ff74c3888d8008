"""Whole reconstructions with each coarse-stage model: final accuracy and time per stage (issue 16, item 1).

    python -m benchmarks run regularisation make-scenes --scenes beads,letters128      # scenes into out/scenes/
    OMP_NUM_THREADS=1 python -m benchmarks run coarse_recon --scenes sample,beads --models envelope,envelope_batched,multislice

Every run uses the default settings except ``coarse_model``: ``envelope`` (the envelope model, path chosen by
device: one slice at a time on the CPU), ``envelope_batched`` (the same model forced onto its batched path,
:meth:`~napari_fdt.model.envelope.EnvelopeModel.images_batched`, which CUDA uses; the batched flag is patched in
here, it is not a setting) and ``multislice``. Records the relative Δn error against the truth, the validation
error, the solver's seconds per iteration of each stage and the wall time; appends one JSON object per line to
``benchmarks/results/coarse_recon_<device>.jsonl``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from benchmarks._results import append_row, results_file

ROOT = Path(__file__).resolve().parents[1]


def run(scene: str, model: str, device: str) -> dict:
    from benchmarks.scenes import SCENES
    from napari_fdt import read_acquisition, read_volume_tiff
    from napari_fdt.model.envelope import EnvelopeModel
    from napari_fdt.recon.assess.metrics import relative_delta_n_error
    from napari_fdt.recon.run.solver import Reconstructor
    from napari_fdt.recon.settings.config import SolverConfig

    folder, _ = SCENES[scene]
    acq = read_acquisition(folder)
    truth, _ = read_volume_tiff(folder / "ground_truth_ri.tif")
    cfg = SolverConfig.from_dict({**SolverConfig().to_dict(), "coarse_model": "multislice" if model == "multislice" else "envelope"})
    original = EnvelopeModel.__init__
    if model == "envelope_batched":
        def batched_init(self, *a, **k):
            k["batched"] = True
            original(self, *a, **k)
        EnvelopeModel.__init__ = batched_init
    try:
        t0 = time.perf_counter()
        rec = Reconstructor(acq, cfg, device=device)
        for _ in rec.run():
            pass
        wall = time.perf_counter() - t0
    finally:
        EnvelopeModel.__init__ = original
    return {"scene": scene, "model": model, "device": device,
            "relative_delta_n_error": relative_delta_n_error(rec.delta_n_full(), truth - acq.optics.n_background),
            "validation_error": rec.stages[-1].validation_error if rec.stages else None,
            "seconds_per_iteration": {f"x{r.factor}": r.seconds_per_iteration for r in rec.stages},
            "stage_models": [r.model for r in rec.stages], "wall_s": wall,
            "tv": None if rec.tv_choice is None else rec.tv_choice.to_dict()}  # + the machine's fields (append_row)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", default="sample,beads")
    p.add_argument("--models", default="envelope,envelope_batched,multislice")
    p.add_argument("--device", default="cpu")
    args = p.parse_args()
    out = results_file("coarse_recon", args.device)
    for scene in args.scenes.split(","):
        for model in args.models.split(","):
            row = run(scene, model, args.device)
            print(json.dumps(row), flush=True)
            append_row(out, row, args.device)


if __name__ == "__main__":
    main()
