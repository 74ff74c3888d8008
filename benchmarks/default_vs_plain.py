"""One default run, or one plain pass, of a suite scene: wall time, the TV choice, the parts kept, the Δn error and the
validation error, as one JSON line (docs/decisions/one-pass-default-vs-plain.md).

    python -m benchmarks run default_vs_plain SCENE [--seed 0]                         # the defaults
    python -m benchmarks run default_vs_plain SCENE --plain 1 [--set '{"calibrate_pupil": true}']   # τ_xy 1, τ_z 0.5 given
    python -m benchmarks run default_vs_plain SCENE --set '{"field_window": "full"}'   # the defaults but one
    PYTHONPATH=/path/to/older/checkout/src python -m benchmarks run default_vs_plain SCENE   # the same with older code

SCENE: a name of ``benchmarks/regularisation.py``'s suite (``make-scenes`` simulates them) or a folder under out/scenes.
"""

from __future__ import annotations

import argparse
import json
import time

from benchmarks.scenes import folder_of  # noqa: E402
from napari_fdt import read_acquisition, read_volume_tiff  # noqa: E402
from napari_fdt.recon.assess.metrics import relative_delta_n_error  # noqa: E402
from napari_fdt.recon.run.solver import Reconstructor  # noqa: E402
from napari_fdt.recon.settings.config import SolverConfig  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--plain", type=float, default=None, help="a plain pass at τ_xy PLAIN (τ_z = PLAIN/2)")
    ap.add_argument("--set", default="{}", help="more settings (of the defaults, or of the plain pass), as JSON")
    args = ap.parse_args()
    folder = folder_of(args.scene)
    acq = read_acquisition(folder)
    truth, _ = read_volume_tiff(folder / "ground_truth_ri.tif")
    extra = {} if args.plain is None else {"tv_xy_weight": args.plain, "tv_z_weight": args.plain / 2}
    extra.update(json.loads(args.set))
    cfg = SolverConfig.from_dict({**SolverConfig().to_dict(), "seed": args.seed, **extra})
    t0 = time.perf_counter()
    rec = Reconstructor(acq, cfg, device="cpu")
    for _ in rec.run():
        pass
    wall = time.perf_counter() - t0
    c = rec.tv_choice
    print(json.dumps({"scene": args.scene, "seed": args.seed, "plain": args.plain, "set": json.loads(args.set), "wall_s": round(wall, 1),
                      "tau": c.tv_xy_weight if c else None, "trials": len(c.trials) if c else 0,
                      "trials_s": round(c.seconds, 1) if c else 0, "parts": [p for p, on in rec.parts.items() if on],
                      "dn_error": round(float(relative_delta_n_error(rec.delta_n_full(), truth - acq.optics.n_background)), 4),
                      "validation": rec.stages[-1].validation_error}), flush=True)


if __name__ == "__main__":
    main()
