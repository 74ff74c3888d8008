"""Regularisation on a suite of scenes: "auto", no TV and a TV sweep, with the validation error against the true error.

Usage (repository root)::

    python -m benchmarks run regularisation make-scenes            # simulate the suite's scenes into out/scenes/
    python -m benchmarks run regularisation run --scenes sample,beads --settings auto,0,1,3,10,30 [--set '{"seed": 1}']
    python -m benchmarks run regularisation table                  # docs/ablation.md's regularisation section

Every run is a full reconstruction with the default settings except the TV weights: ``auto`` (the default,
``tv_xy_weight = tv_z_weight = "auto"``), ``0`` (no TV), or a number τ (τ_xy = τ, τ_z = τ/2, as the issue's
"TV 50/25"). Each row records the relative Δn error against the truth, the validation error (the held-out
images), both at the end of every stage, the calibrated sources' error and the wall time. Results are appended,
one JSON object per line, to ``benchmarks/results/regularisation_<device>.jsonl`` (a rerun of the same scene and
setting replaces its row in the table). ``table`` ranks each scene's settings by validation error and by true
error (Spearman's ρ over the suite) and writes the Markdown section of ``docs/ablation.md``.

The scenes (``make-scenes``; the commands are in :data:`benchmarks.scenes.SUITE`): the bundled sample; issue 12's 128² letters
scene with 196 sources 50 µm deep; beads and cells (64²×8, 49 sources 30 µm deep); deep sources (120 µm) with the
camera focused 8 µm inside the volume (NA 0.5, 0.5 µm pixels). On a GPU, ``demo`` is the authors' 512²×14 geometry with 1521 sources.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from benchmarks._results import append_row, code_version, results_file
from benchmarks.scenes import SCENE_DIR, SUITE, make_scenes  # noqa: F401 (re-exported)

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "ablation.md"
SWEEP = ("0", "1", "3", "10", "30")  # issue 25's sweep (before 2026-11-26: 0, 1, 5, 10, 50, 200)

#: name → (acquisition folder, the ``fdt simulate`` arguments that make it; None: bundled)
# the suite's scenes and how to make them: benchmarks/scenes.py (the one registry)
SCENES = SUITE


def config_for(setting: str, base: dict | None = None):
    """The solver configuration of a row: the defaults with TV ``auto``, off (``0``) or τ_xy = τ, τ_z = τ/2."""
    from napari_fdt.recon.settings.config import SolverConfig

    d = dict(base or {})
    if setting == "auto":
        d.update(tv_xy_weight="auto", tv_z_weight="auto")
    else:
        tau = float(setting)
        d.update(tv_xy_weight=tau, tv_z_weight=tau / 2)
    return SolverConfig.from_dict({**SolverConfig().to_dict(), **d})


def run_one(scene: str, setting: str, device: str, base: dict | None = None, on_snapshot=None) -> dict:
    """One full reconstruction; the row of the results file. ``on_snapshot(rec, snap, truth_src, t0)``, if given, sees
    every snapshot (``benchmarks/source_positions.py`` traces the sources with it)."""
    from napari_fdt import read_acquisition, read_volume_tiff
    from napari_fdt.recon.assess.metrics import relative_delta_n_error
    from napari_fdt.recon.run.report import evaluate_images, source_errors
    from napari_fdt.recon.run.solver import Reconstructor

    folder, _ = SCENES[scene]
    acq = read_acquisition(folder)
    truth, _ = read_volume_tiff(folder / "ground_truth_ri.tif")
    true_dn = truth - acq.optics.n_background
    truth_src = np.array(json.loads((folder / "ground_truth_sources_um.json").read_text())["sources_um"])
    cfg = config_for(setting, base)
    commit = code_version()  # at the start: the code this process imported
    t0 = time.perf_counter()
    rec = Reconstructor(acq, cfg, device=device)
    stages = []
    for snap in rec.run():
        if snap.phase == "tv_choice":  # the TV choice (its stages before the trials, the trials), not the run's stages
            continue
        if on_snapshot is not None:
            on_snapshot(rec, snap, truth_src, t0)
        if snap.stage_complete:
            stages.append({"stage": snap.stage, "factor": snap.factor, "validation_error": snap.validation_error,
                           "relative_delta_n_error": relative_delta_n_error(snap.delta_n_full(), true_dn)})
    wall = time.perf_counter() - t0
    _, fit = evaluate_images(rec)
    src = source_errors(rec.sources_um(), truth_src)
    val = rec.stages[-1].validation_error if rec.stages else None
    return {
        "scene": scene, "setting": setting, "device": device, "config_overrides": base or {},
        "relative_delta_n_error": relative_delta_n_error(rec.delta_n_full(), true_dn), "validation_error": val,
        "stages": stages, "tv": None if rec.tv_choice is None else rec.tv_choice.to_dict(),
        "parts_needed": [] if rec.parts_choice is None else rec.parts_choice.needed,
        "finest_iterations": rec.config.stages[-1].iterations, "image_relative_error": fit["image_relative_error"],
        "source_lateral_rms_um": src["lateral_rms_um"], "source_depth_rms_um": src["depth_rms_um"], "wall_s": wall,
        "iterations": cfg.total_iterations, "date": time.strftime("%Y-%m-%d"), "commit": commit,
    }  # with the machine's fields (benchmarks._results.append_row)


def results_path(device: str) -> Path:
    return results_file("regularisation", device)


def _effective_overrides(overrides: dict) -> dict:
    """The overrides that differ from the current defaults (a row made with an override equal to today's default
    belongs to the default rows)."""
    from napari_fdt.recon.settings.config import SolverConfig

    defaults = SolverConfig().to_dict()
    return {k: v for k, v in overrides.items() if defaults.get(k) != v}


def load_rows(paths: list[Path], since: str | None = None) -> list[dict]:
    """Rows of the results files, the last of each (scene, setting, overrides) kept; with ``since`` (YYYY-MM-DD) only
    rows made on or after that day (rows of older code stay in the file as history)."""
    rows: dict[tuple, dict] = {}
    for p in paths:
        if not p.is_file():
            continue
        for line in p.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                if since is not None and r.get("date", "") < since:
                    continue
                r["config_overrides"] = _effective_overrides(r.get("config_overrides", {}))
                rows[(r["scene"], r["setting"], json.dumps(r.get("config_overrides", {}), sort_keys=True))] = r
    return list(rows.values())


def spearman(a: list[float], b: list[float]) -> float:
    """Spearman's rank correlation (average ranks for ties)."""
    def ranks(v):
        v = np.asarray(v, dtype=np.float64)
        order = np.argsort(v, kind="mergesort")
        r = np.empty(len(v))
        r[order] = np.arange(len(v), dtype=np.float64)
        for x in np.unique(v):  # ties share their mean rank
            r[v == x] = r[v == x].mean()
        return r
    ra, rb = ranks(a), ranks(b)
    if ra.std() == 0 or rb.std() == 0:
        return float("nan")
    return float(np.corrcoef(ra, rb)[0, 1])


def table(rows: list[dict]) -> str:
    """The Markdown section: per scene, every setting's error, validation error, time; auto against the sweep."""
    order = ["auto", *SWEEP]
    scenes = [s for s in SCENES if any(r["scene"] == s and not r.get("config_overrides") for r in rows)]
    out = ["| scene | setting | relative Δn error | validation error | sources (lateral RMS, µm) | wall time (s) | τ chosen (xy / z) |",
           "|---|---|---|---|---|---|---|"]
    summary = ["| scene | best of the sweep (τ: error) | auto: error | auto / best | auto / no TV | Spearman ρ (validation vs true, sweep) |",
               "|---|---|---|---|---|---|"]
    rhos = []
    for s in scenes:
        by = {r["setting"]: r for r in rows if r["scene"] == s and not r.get("config_overrides")}
        for k in [k for k in order if k in by]:
            r = by[k]
            tv = r.get("tv") or {}
            chosen = f"{tv.get('tv_xy_weight', ''):g} / {tv.get('tv_z_weight', ''):g}" if tv else ""
            val = "" if r["validation_error"] is None else f"{r['validation_error']:.4f}"
            out.append(f"| {s} | {k} | {r['relative_delta_n_error']:.3f} | {val} | {r['source_lateral_rms_um']:.3f} | "
                       f"{r['wall_s']:.0f} | {chosen} |")
        sweep = [k for k in SWEEP if k in by]
        if len(sweep) >= 3 and all(by[k]["validation_error"] is not None for k in sweep):
            rho = spearman([by[k]["validation_error"] for k in sweep], [by[k]["relative_delta_n_error"] for k in sweep])
            rhos.append(rho)
        else:
            rho = float("nan")
        if sweep:
            best = min(sweep, key=lambda k: by[k]["relative_delta_n_error"])
            b = by[best]["relative_delta_n_error"]
            a = by["auto"]["relative_delta_n_error"] if "auto" in by else float("nan")
            none = by["0"]["relative_delta_n_error"] if "0" in by else float("nan")
            summary.append(f"| {s} | {best}: {b:.3f} | {a:.3f} | {a / b:.3f} | {a / none:.3f} | {rho:.2f} |")
    all_rho = f"{np.nanmean(rhos):.2f}" if rhos else "n/a"
    text = "\n".join(out) + "\n\n" + "\n".join(summary) + f"\n\nMean Spearman ρ over the scenes: {all_rho}.\n"
    # run-to-run spread: the same scene and setting with other seeds (batch order; `run --set '{"seed": 1}'`)
    spread: dict[tuple[str, str], dict[int, float]] = {}
    for r in rows:
        extra = r.get("config_overrides") or {}
        if set(extra) <= {"seed"}:
            spread.setdefault((r["scene"], r["setting"]), {})[int(extra.get("seed", 0))] = r["relative_delta_n_error"]
    spread = {k: v for k, v in spread.items() if len(v) > 1}
    means = seed_means(spread)
    if means:
        text += ("\nMeans over seeds (the settings run with every seed that \"auto\" was run with; one seed resolves a few per cent at "
                 "best, so these are what \"within 5 %\" is read on):\n\n"
                 "| scene | seeds | mean relative Δn error per setting | best of the sweep | auto / best |\n|---|---|---|---|---|\n")
        for scene, (seeds, by_setting, best, ratio) in means.items():
            cells = ", ".join(f"{k}: {v:.3f}" for k, v in by_setting.items())
            text += f"| {scene} | {', '.join(map(str, seeds))} | {cells} | {best}: {by_setting[best]:.3f} | {ratio:.3f} |\n"
    if spread:
        text += ("\nRun-to-run spread (the same settings with other seeds, i.e. another batch order):\n\n"
                 "| scene | setting | relative Δn error per seed | range |\n|---|---|---|---|\n")
        for (scene, setting), by_seed in sorted(spread.items()):
            errs = ", ".join(f"{seed}: {e:.3f}" for seed, e in sorted(by_seed.items()))
            text += f"| {scene} | {setting} | {errs} | {min(by_seed.values()):.3f}–{max(by_seed.values()):.3f} |\n"
    return text


def seed_means(spread: dict[tuple[str, str], dict[int, float]]) -> dict[str, tuple[list[int], dict[str, float], str, float]]:
    """Per scene with "auto" run over several seeds: those seeds, the mean error of every setting run with all of them,
    the sweep's best setting by that mean and auto's mean over it."""
    out = {}
    for scene in dict.fromkeys(sc for sc, _ in spread):
        auto = spread.get((scene, "auto"))
        if not auto:
            continue
        seeds = sorted(auto)
        by = {k: float(np.mean([spread[(scene, k)][sd] for sd in seeds])) for k in ["auto", *SWEEP]
              if (scene, k) in spread and set(seeds) <= set(spread[(scene, k)])}
        sweep = [k for k in by if k != "auto"]
        if sweep:
            best = min(sweep, key=by.get)
            out[scene] = (seeds, by, best, by["auto"] / by[best])
    return out


def write_doc(rows: list[dict], since: str | None = None) -> None:
    """Replace the regularisation section of docs/ablation.md (between its markers) with the current table."""
    start, end = "<!-- regularisation:start -->", "<!-- regularisation:end -->"
    text = DOC.read_text(encoding="utf-8")
    hw = sorted({f"{r['device']} ({r['threads']} thread{'s' if r['threads'] > 1 else ''}, {r['cpu']}, torch {r['torch']}, {r['date']})"
                 for r in rows})
    commits = sorted({r.get("commit", "?") for r in rows})
    scenes = "; ".join(f"*{name}*: " + ("the bundled `sample_data/letters`" if args is None else f"`fdt simulate {args}`")
                       for name, (_, args) in SCENES.items() if any(r["scene"] == name for r in rows))
    body = "\n".join([
        start,
        "Made by `python -m benchmarks run regularisation run --scenes SCENES --settings auto,0,1,3,10,30 [--set '{\"seed\": 1}']` and",
        f"`python -m benchmarks run regularisation table --write{' --since ' + since if since else ''}` (every row, with each stage's "
        "errors, the trials of \"auto\" and the model parts kept,",
        "is in `benchmarks/results/regularisation_<device>.jsonl`; older rows stay there as history). Each row is a full",
        "reconstruction with the default settings (10 % of the images held out) except the TV weights: `auto` (the default),",
        "`0` (no TV) or τ (τ_xy = τ, τ_z = τ/2). Relative Δn error against the truth; validation error of the held-out",
        "images at the end; the calibrated sources' lateral RMS error; wall time.",
        f"Scenes (seed 0): {scenes}.",
        f"Hardware: {'; '.join(hw)}; code: {', '.join(commits)}. The runs took one thread each, two to four at a time on",
        "the 2 cores, so their wall times compare only roughly; the cost of \"auto\" on a quiet machine is in docs/solver.md.",
        "",
        table(rows),
        end,
    ])
    if start in text:
        text = text[: text.index(start)] + body + text[text.index(end) + len(end):]
    else:
        text = text.rstrip() + "\n\n## Regularisation: \"auto\" against a TV sweep\n\n" + body + "\n"
    DOC.write_text(text, encoding="utf-8")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("make-scenes")
    m.add_argument("--scenes", default="letters128,beads,cells,deep")
    m.add_argument("--device", default="cpu")
    r = sub.add_parser("run")
    r.add_argument("--scenes", default="sample,letters128,beads,cells,deep")
    r.add_argument("--settings", default="auto," + ",".join(SWEEP))
    r.add_argument("--device", default="cpu")
    r.add_argument("--set", default="{}", help="JSON object of other settings for every row (e.g. '{\"lr_sources_um\": 0.05}')")
    t = sub.add_parser("table")
    t.add_argument("--devices", default="cpu,cuda")
    t.add_argument("--write", action="store_true", help="write the section of docs/ablation.md")
    t.add_argument("--since", default=None, help="only rows made on or after this day (YYYY-MM-DD): the current code's")
    args = p.parse_args(argv)
    if args.cmd == "make-scenes":
        make_scenes(args.scenes.split(","), args.device)
    elif args.cmd == "run":
        make_scenes(args.scenes.split(","), args.device)
        out = results_path(args.device)
        base = json.loads(args.set)
        for scene in args.scenes.split(","):
            for setting in args.settings.split(","):
                row = run_one(scene, setting, args.device, base)
                append_row(out, row, args.device)
                st = " ".join(f"x{s['factor']}:{s['relative_delta_n_error']:.3f}/{(s['validation_error'] or 0):.4f}" for s in row["stages"])
                print(f"{scene:10s} {setting:5s} err {row['relative_delta_n_error']:.3f} val {row['validation_error'] or float('nan'):.4f} "
                      f"src {row['source_lateral_rms_um']:.3f} µm {row['wall_s']:.0f} s  [{st}] {row['tv'] or ''}", flush=True)
    else:
        rows = load_rows([results_path(d) for d in args.devices.split(",")], args.since)
        print(table(rows))
        if args.write:
            write_doc(rows, args.since)


if __name__ == "__main__":
    main()
