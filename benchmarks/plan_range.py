"""The plan's range at a run's start against the run: ``fdt plan``'s seconds where no model part is kept and where the
costliest are, and the measured solver seconds, per acquisition (issue 48, item 3).

    python -m benchmarks run plan_range ACQ [ACQ ...] [--short] [--config NAME=CONFIG.json] [--out-dir DIR] [--device cpu]
        [--write benchmarks/results/plan_range_cpu.json]

Each acquisition is planned (:func:`napari_fdt.recon.loop.plan.plan_for`, as ``fdt plan`` does) and then reconstructed
with the defaults, one process at a time (``python -m napari_fdt reconstruct ACQ --out DIR/NAME.tif --device cpu``; a
report ``DIR/NAME.json`` already there is read instead of running again). ``--short`` adds a run of the first
acquisition with the issue's short schedule (stages x2 and x1 of 20 iterations, batch 4), ``--config NAME=FILE`` one with
any configuration. The record keeps each acquisition's geometry, so ``tests/test_plan.py`` plans it again without the images.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from benchmarks._results import code_version, command, machine

#: the short schedule of issue 48 ("2 s planned against 268 s measured" when it was filed)
SHORT_SCHEDULE = {"stages": [{"factor": 2, "iterations": 20}, {"factor": 1, "iterations": 20}], "batch_size": 4}


def _geometry(acq) -> dict:
    """What the plan reads of an acquisition: optics, image shape, sources, the camera as the files state it."""
    return {"optics": acq.optics.to_dict(), "image_shape": list(acq.image_shape), "sources_um": acq.sources_um.tolist(),
            "extra": {**{k: v for k, v in acq.extra.items() if k in ("pixel_integration", "pupil_edge")},
                      **({"simulated": {}} if "simulated" in acq.extra else {})}}  # (a simulated folder's camera)


def recorded_acquisition(row: dict):
    """The acquisition a record's row was planned on, without its images (zeros): what :func:`_geometry` kept."""
    import numpy as np

    from napari_fdt.data.acquisition import Acquisition
    from napari_fdt.physics.optics import Optics

    src = np.asarray(row["sources_um"], dtype=np.float64)
    return Acquisition(np.zeros((len(src), *row["image_shape"]), np.float32), Optics(**row["optics"]), src, extra=row["extra"])


def measure(path: Path, name: str, config_path: Path | None, out_dir: Path, device: str) -> dict:
    from napari_fdt.data.io import read_acquisition
    from napari_fdt.recon.loop.plan import plan_for
    from napari_fdt.recon.settings.config import SolverConfig

    acq = read_acquisition(path)
    config = SolverConfig.from_dict(json.loads(config_path.read_text())) if config_path else SolverConfig()
    plan, _ = plan_for(acq, config, device)
    report = out_dir / f"{name}.json"
    if not report.exists():
        cmd = [sys.executable, "-m", "napari_fdt", "reconstruct", str(path), "--out", str(out_dir / f"{name}.tif"),
               "--device", device, "--quiet", "--overwrite", *(["--config", str(config_path)] if config_path else []),
               *(["--truth", str(path / "ground_truth_ri.tif")] if (path / "ground_truth_ri.tif").exists() else [])]
        subprocess.run(cmd, check=True)
    rep = json.loads(report.read_text())
    measured = float(rep["seconds_total"])
    row = {"name": name, "acquisition": str(path), "config": json.loads(config_path.read_text()) if config_path else None,
           **_geometry(acq), "plan_s": plan.predicted_s, "plan_most_s": plan.most_s,
           "plan_at_the_end_s": rep["plan"]["predicted_total_s"], "measured_s": measured,
           "parts_chosen": sorted(p for p, on in (rep["model_parts"].get("parts") or {}).items()
                                  if on and (rep["model_parts"].get("chosen_by") or {}).get(p) == "validation"),
           "delta_n_error": ((rep.get("metrics") or {}).get("relative_delta_n_error")),
           "phases": [{"name": p["name"], "predicted_s": p["predicted_s"], "seconds": p.get("seconds")}
                      for p in rep["plan"]["phases"]]}
    lo, hi = row["plan_s"], row["plan_most_s"] or row["plan_s"]
    print(f"{name}: plan {lo:.1f} s, up to {hi:.1f} s; at the end {row['plan_at_the_end_s']:.1f} s; measured {measured:.1f} s "
          f"({measured / lo:.2f}x the plan, {measured / hi:.2f}x its top); parts chosen: {', '.join(row['parts_chosen']) or 'none'}",
          flush=True)
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("acquisitions", nargs="+", type=Path)
    ap.add_argument("--config", action="append", default=[], help="NAME=CONFIG.json: a run of the first acquisition with it")
    ap.add_argument("--short", action="store_true", help="a run of the first acquisition with the issue's short schedule "
                    "(stages x2 and x1 of 20 iterations, batch 4), named 'short'")
    ap.add_argument("--out-dir", type=Path, default=Path("/tmp/plan_range"))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--write", type=Path, default=None)
    args = ap.parse_args(argv)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    runs = [(a, a.name, None) for a in args.acquisitions]
    runs += [(args.acquisitions[0], n, Path(f)) for n, f in (c.split("=", 1) for c in args.config)]
    if args.short:
        short = args.out_dir / "short_schedule.json"
        short.write_text(json.dumps(SHORT_SCHEDULE))
        runs.append((args.acquisitions[0], "short", short))
    rows = [measure(a, n, c, args.out_dir, args.device) for a, n, c in runs]
    if args.write:
        record = {"what": __doc__.splitlines()[0], "command": command(),
                  "hardware": machine(args.device), "code": code_version(),
                  "note": "one process at a time on an idle machine; measured_s: the report's seconds_total (the solver's)",
                  "runs": rows}
        tmp = args.write.with_suffix(".tmp")
        tmp.write_text(json.dumps(record, indent=1) + "\n")
        tmp.replace(args.write)
    return 0


if __name__ == "__main__":
    sys.exit(main())
