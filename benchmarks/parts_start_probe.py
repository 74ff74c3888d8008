"""Issue 27 probe (deleted after its run; record: docs/decisions/model-parts.md, "Forward-accuracy parts"): the parts'
paired test of sub-slices and of the 2x field grid made at the finest stage's *start* (the x2 stage's volume, trained
with the envelope model, so biased towards neither finest model) instead of its end, on held-out + training images.

    python -m benchmarks run parts_start_probe SCENE_DIR SEED       # one JSON line to stdout, one row to results
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time

from benchmarks._results import append_row, results_file
from napari_fdt.data.io import read_acquisition
from napari_fdt.recon.config import SolverConfig
from napari_fdt.recon.model_parts import decide
from napari_fdt.recon.parts_search import choice_errors
from napari_fdt.recon.parts_switch import set_parts
from napari_fdt.recon.solver import Reconstructor


def main(argv: list[str] | None = None) -> int:
    scene, seed = (argv or sys.argv[1:])[:2]
    rec = Reconstructor(read_acquisition(scene), SolverConfig(seed=int(seed)), device="cpu")
    for _ in rec.run():
        if rec.completed_stages >= 2:  # the x2 stage's end: stop before the finest stage trains
            break
    work = rec._begin_stage(2)
    base, cfg = dict(rec.parts), rec.config
    ref, ref_each = choice_errors(rec, work.stage, work.mask)
    row = {"scene": scene, "seed": int(seed), "reference_error": ref}
    for name, parts, grid in (("sub_slices", {"sub_slices": True}, 1), ("field_grid", {}, 2), ("both", {"sub_slices": True}, 2)):
        set_parts(rec, {**base, **parts})
        rec.config = dataclasses.replace(cfg, field_oversampling=grid)
        stage = rec._build_stage(2)
        t0 = time.perf_counter()
        err, each = choice_errors(rec, stage, rec._loss_mask(stage))
        v = decide(ref_each, each)
        row[name] = {"error": err, "relative_change": -v["improvement"] / ref, "z": v["improvement"] / v["standard_error"],
                     "on": v["on"], "seconds": time.perf_counter() - t0}
    rec.config = cfg
    set_parts(rec, base)
    append_row(results_file("parts_start_probe", "cpu"), row, "cpu")
    print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
