"""Rules for the automatic TV weight, compared offline on recorded runs (issue 12, "auto within 5 % of the best TV").

Usage (repository root)::

    python -m benchmarks run tv_rule_offline --since 2026-11-25          # table of rules × scenes, means over seeds
    python -m benchmarks run tv_rule_offline --since 2026-11-25 --markdown
    python -m benchmarks run tv_rule_offline --since 2026-11-26 --whole-path   # the tolerance rule on whole runs
    python -m benchmarks run tv_rule_offline --since 2026-11-26 --coarse-paths # ... on the finest stage's first iterations
    python -m benchmarks run tv_rule_offline --since 2026-11-26 --two-candidates   # auto's weight against the next larger

An "auto" run is bit-identical to the run given its chosen weight as a number (``tests/test_regularisation.py``), and
its row in ``benchmarks/results/regularisation_cpu.jsonl`` keeps every trial of the pilot with its per-image held-out
errors. So any rule that reads only those trials can be evaluated without running it: its choice on a (scene, seed) is
a weight of the path, and its outcome is the fixed-weight row of that weight and seed (``regularisation.py run
--settings 0,1,3,10 --set '{"seed": S}'``). A rule whose choice has no such row is reported as missing, never guessed.

The rules: the paired k-standard-error rule of ``napari_fdt.recon.loop.regularisation.pick`` for k = 0 (the plain lowest
validation error), 1 (the default) and 2. Each scene's reference is the best weight of the sweep by its mean error
over the same seeds (weights run with every seed that has an "auto" row).
"""

from __future__ import annotations

import argparse

import numpy as np

from benchmarks._results import RESULTS, read_rows  # noqa: E402
from benchmarks.regularisation import SCENES, load_rows  # noqa: E402
from napari_fdt.recon.loop.regularisation import pick  # noqa: E402

RULES = {"argmin (0 SE)": 0.0, "1 SE (default)": 1.0, "2 SE": 2.0}


def _seed(row: dict) -> int:
    return int((row.get("config_overrides") or {}).get("seed", 0))


def evaluate(rows: list[dict]) -> list[dict]:
    """One record per scene: seeds, the sweep's mean errors, and per rule its choices, mean error and ratio to the best."""
    out = []
    for scene in SCENES:
        rs = [r for r in rows if r["scene"] == scene and set(r.get("config_overrides") or {}) <= {"seed"}]
        autos = {_seed(r): r for r in rs if r["setting"] == "auto" and r.get("tv") and r["tv"].get("trials")}
        if not autos:
            continue
        fixed: dict[float, dict[int, float]] = {}
        for r in rs:
            if r["setting"] != "auto":
                fixed.setdefault(float(r["setting"]), {})[_seed(r)] = r["relative_delta_n_error"]
        for sd, r in autos.items():  # an auto run is the fixed run at its choice
            fixed.setdefault(float(r["tv"]["tv_xy_weight"]), {}).setdefault(sd, r["relative_delta_n_error"])
        seeds = sorted(autos)
        means = {tau: float(np.mean([by[s] for s in seeds])) for tau, by in fixed.items() if set(seeds) <= set(by)}
        if not means:
            continue
        best = min(means, key=means.get)
        rec = {"scene": scene, "seeds": seeds, "means": dict(sorted(means.items())), "best": best, "rules": {}}
        for name, k in RULES.items():
            chosen = {s: float(pick(autos[s]["tv"]["trials"], k)["tau"]) for s in seeds}
            errs = [fixed.get(chosen[s], {}).get(s) for s in seeds]
            missing = [s for s, e in zip(seeds, errs) if e is None]
            mean = None if missing else float(np.mean(errs))
            rec["rules"][name] = {"chosen": chosen, "errors": errs, "mean": mean, "missing": missing,
                                  "ratio": None if mean is None else mean / means[best]}
        out.append(rec)
    return out


PATH = (1.0, 3.0, 10.0, 30.0)
TOLERANCES = (0.0, 0.02, 0.05, 0.08)


def _fixed_runs(rows: list[dict]) -> dict[tuple[str, int, float], dict]:
    """The fixed-weight rows of the plain sweep (no settings but the seed), by (scene, seed, τ_xy)."""
    return {(r["scene"], _seed(r), float(r["setting"])): r for r in rows
            if set(r.get("config_overrides") or {}) <= {"seed"} and r["setting"] != "auto"}


def _tolerance_pick(errors: dict[float, float], delta: float) -> float:
    """The largest τ whose held-out error is within (1 + ``delta``) of the smallest of ``errors`` (τ → error)."""
    return max(t for t in errors if errors[t] <= (1 + delta) * min(errors.values()))


def whole_path(rows: list[dict]) -> str:
    """What the held-out images say when every weight has run the whole path: for each stage's end (×4, ×2, finest)
    and tolerance δ, the rule "the largest τ of :data:`PATH` whose held-out error at that stage's end is within
    (1 + δ) of the smallest", applied to the fixed-weight runs of each (scene, seed); its outcome is that run's final
    Δn error. Table: the mean over seeds over the best fixed weight's mean (τ 0 included). Not a rule a run can
    afford (every weight's whole run); it asks whether the held-out images can rank the weights at all."""
    runs: dict[tuple[str, int], dict[float, dict]] = {}
    for (scene, seed, tau), r in _fixed_runs(rows).items():
        runs.setdefault((scene, seed), {})[tau] = r
    runs = {k: v for k, v in runs.items() if set(PATH) | {0.0} <= set(v)}
    scenes = sorted({sc for sc, _ in runs})
    lines = ["| stage's end | δ | " + " | ".join(scenes) + " |", "|---|---|" + "---|" * len(scenes)]
    for stage in range(3):
        for delta in TOLERANCES:
            cells = []
            for sc in scenes:
                keys = sorted(k for k in runs if k[0] == sc)
                got = []
                for k in keys:
                    tau = _tolerance_pick({t: runs[k][t]["stages"][stage]["validation_error"] for t in PATH}, delta)
                    got.append(runs[k][tau]["relative_delta_n_error"])
                best = min(np.mean([runs[k][t]["relative_delta_n_error"] for k in keys]) for t in (0.0, *PATH))
                cells.append(f"{np.mean(got) / best:.2f}")
            name = ("×4", "×2", "finest")[stage]
            lines.append(f"| {name} | {delta:g} | " + " | ".join(cells) + " |")
    n = {sc: sum(1 for k in runs if k[0] == sc) for sc in scenes}
    return "\n".join(lines) + "\n\nseeds per scene: " + ", ".join(f"{sc} {c}" for sc, c in n.items())


def coarse_paths(rows: list[dict], probes: list[dict]) -> str:
    """The tolerance rule of :func:`whole_path` applied to the held-out errors that ``tv_coarse_paths.py`` recorded at
    the finest stage's start (iteration 0) and after 10, 20 and 40 of its iterations, each weight's stages before
    having run at that weight; the outcome of a choice is the fixed-weight run's final Δn error (same scene, seed)."""
    final = {k: r["relative_delta_n_error"] for k, r in _fixed_runs(rows).items()}
    seen: dict[tuple[str, int], dict[float, dict[int, float]]] = {}
    for pr in probes:
        seen.setdefault((pr["scene"], int(pr["seed"])), {})[float(pr["tau"])] = {t["iteration"]: t["validation_error"] for t in pr["trace"]}
    keys = sorted(k for k, by in seen.items() if all((k[0], k[1], t) in final for t in by) and len(by) > 1)
    scenes = sorted({sc for sc, _ in keys})
    marks = sorted({it for by in seen.values() for tr in by.values() for it in tr})
    lines = ["| finest iteration | δ | " + " | ".join(scenes) + " |", "|---|---|" + "---|" * len(scenes)]
    for it in marks:
        for delta in (0.0, 0.03, 0.05, 0.08, 0.12):
            cells = []
            for sc in scenes:
                ks = [k for k in keys if k[0] == sc]
                got = []
                for k in ks:
                    tau = _tolerance_pick({t: tr[it] for t, tr in seen[k].items() if it in tr}, delta)
                    got.append(final[(k[0], k[1], tau)])
                taus = {t for (s_, _, t) in final if s_ == sc}
                best = min(np.mean([final[(sc, k[1], t)] for k in ks]) for t in taus
                           if all((sc, k[1], t) in final for k in ks))
                cells.append(f"{np.mean(got) / best:.2f}")
            lines.append(f"| {it} | {delta:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n\nseeds: " + ", ".join(f"{sc} {sum(1 for k in keys if k[0] == sc)}" for sc in scenes)


def two_candidates(rows: list[dict], probes: list[dict]) -> str:
    """Two candidates only, as one run could afford them: the weight the ``"auto"`` run chose (its row in the sweep) and
    the next larger weight of :data:`PATH`, each after its own coarse stages and ``it`` finest iterations
    (``tv_coarse_paths.py``'s rows). Rules: the larger weight when its held-out error is within (1 + δ) of the chosen
    one's (``tol δ``), or when the paired per-image test of the log errors gives z ≤ k (``z k``: k = 1, the larger
    weight unless it is worse by a standard error). Outcome: the fixed-weight run's final Δn error; cells, the mean over
    seeds over the best fixed weight's mean."""
    final = {k: r["relative_delta_n_error"] for k, r in _fixed_runs(rows).items()}
    auto = {(r["scene"], _seed(r)): float(r["tv"]["tv_xy_weight"]) for r in rows
            if r["setting"] == "auto" and set(r.get("config_overrides") or {}) <= {"seed"} and r.get("tv")}
    seen: dict[tuple[str, int], dict[float, dict[int, tuple[float, np.ndarray]]]] = {}
    for pr in probes:
        seen.setdefault((pr["scene"], int(pr["seed"])), {})[float(pr["tau"])] = {
            t["iteration"]: (t["validation_error"], np.asarray(t["image_errors"])) for t in pr["trace"]}
    scenes = sorted({k[0] for k in seen if k in auto})
    marks = sorted({it for by in seen.values() for tr in by.values() for it in tr})
    lines = ["| finest iteration | rule | " + " | ".join(scenes) + " |", "|---|---|" + "---|" * len(scenes)]
    for it in marks:
        for rule in ("tol 0", "tol 0.03", "tol 0.05", "tol 0.08", "z 1"):
            cells = []
            for sc in scenes:
                ks = sorted(k for k in seen if k[0] == sc and k in auto)
                got = []
                for k in ks:
                    tc = auto[k]
                    pick = tc
                    if tc in PATH[:-1] and {tc, PATH[PATH.index(tc) + 1]} <= set(seen[k]):
                        tn = PATH[PATH.index(tc) + 1]
                        (ec, ic), (en, inn) = seen[k][tc][it], seen[k][tn][it]
                        if rule.startswith("tol"):
                            larger = en <= (1 + float(rule.split()[1])) * ec
                        else:
                            d = np.log(inn) - np.log(ic)
                            larger = d.mean() / (d.std(ddof=1) / np.sqrt(len(d))) <= float(rule.split()[1])
                        pick = tn if larger else tc
                    got.append(final[(sc, k[1], pick)])
                taus = {t for (s_, _, t) in final if s_ == sc}
                best = min(np.mean([final[(sc, k[1], t)] for k in ks]) for t in taus
                           if all((sc, k[1], t) in final for k in ks))
                cells.append(f"{np.mean(got) / best:.2f}")
            lines.append(f"| {it} | {rule} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def markdown(records: list[dict]) -> str:
    lines = ["| scene | seeds | sweep mean errors (τ: error) | best | " + " | ".join(RULES) + " |",
             "|---|---|---|---|" + "---|" * len(RULES)]
    for rec in records:
        sweep = ", ".join(f"{t:g}: {e:.3f}" for t, e in rec["means"].items())
        cells = []
        for name in RULES:
            r = rec["rules"][name]
            ch = "/".join(f"{r['chosen'][s]:g}" for s in rec["seeds"])
            cells.append(f"τ {ch}: " + ("missing " + ",".join(map(str, r["missing"])) if r["mean"] is None
                                       else f"{r['mean']:.3f} ({r['ratio']:.2f}×)"))
        lines.append(f"| {rec['scene']} | {', '.join(map(str, rec['seeds']))} | {sweep} | {rec['best']:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--since", default=None, help="only rows made on or after this day (YYYY-MM-DD)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--markdown", action="store_true")
    p.add_argument("--whole-path", action="store_true", help="the tolerance rule on whole fixed-weight runs")
    p.add_argument("--coarse-paths", action="store_true", help="the tolerance rule on tv_coarse_paths.py's rows")
    p.add_argument("--two-candidates", action="store_true", help="auto's weight against the next larger, on tv_coarse_paths.py's rows")
    args = p.parse_args(argv)
    rows = load_rows([RESULTS / f"regularisation_{args.device}.jsonl"], args.since)
    if args.coarse_paths:
        print(coarse_paths(rows, read_rows(RESULTS / f"tv_coarse_paths_{args.device}.jsonl")))
        return
    if args.two_candidates:
        print(two_candidates(rows, read_rows(RESULTS / f"tv_coarse_paths_{args.device}.jsonl")))
        return
    if args.whole_path:
        print(whole_path(rows))
        return
    records = evaluate(rows)
    if args.markdown:
        print(markdown(records))
        return
    for rec in records:
        print(rec["scene"], "seeds", rec["seeds"], "best", rec["best"], {k: round(v, 3) for k, v in rec["means"].items()})
        for name, r in rec["rules"].items():
            print(f"   {name:16s} chosen {r['chosen']} errors {r['errors']} mean {r['mean']} ratio {r['ratio']}")


if __name__ == "__main__":
    main()
