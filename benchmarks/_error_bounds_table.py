"""The table of ``python -m benchmarks run error_bounds table``: raw scores, split-conformal calibration, coverage.

Every score is a per-voxel map S(v) ≥ 0 made from the result R and its re-simulated reconstructions R_k
(:mod:`benchmarks.error_bounds`); the bound is U = q·S with q the conformal quantile of |R − T| / S over the
calibration scenes' support (pooled voxels, level 0.9). Scores tried (each with its parameters chosen on the
calibration scenes alone, by the smallest mean width there):

* ``constant``: S = 1 (one RI value everywhere: the baseline a map must beat);
* ``contrast``: S = max of |R| over a neighbourhood (the error scales with the object);
* ``spread``: the replicates' standard deviation (noise only: the negative control; it cannot see bias);
* ``bias+spread``: |mean_k R_k − R| + std_k R_k, the parametric bootstrap's bias and spread, over a neighbourhood;
* ``bias+spread+contrast``: that plus α·(the neighbourhood's max |R|);
* ``deflated`` and ``deflated+contrast``: the same with bias and spread divided by the contrast the replicates keep
  (:func:`napari_fdt.recon.assess.bounds.retention`);
* ``halves`` (a control, never shipped): the difference of two half-set reconstructions, as the half-set resolution
  makes them, over a neighbourhood (where every scene has them: ``error_bounds halves``).

Regions (over the support: voxels where the truth or the result is more than ``SUPPORT_DN`` from the background):
objects' interiors, lateral edges, axial caps, background within 2 µm of an object, background farther away.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage

from benchmarks._results import read_rows, results_file, write_document
from benchmarks.error_bounds import FAMILIES, OUT, RESULTS, _optics
from napari_fdt.recon.assess.bounds import conformal_quantile, neighbourhood_max, raw_score

LEVEL = 0.9
#: RI units: a voxel belongs to the support where the truth or the result differs from the background by more
SUPPORT_DN = 1e-3
NEAR_UM = 2.0
#: neighbourhoods tried (slices, pixels) and weights of the contrast term
SIZES = ((1, 1), (3, 3), (3, 5), (3, 7), (3, 9), (5, 9))
ALPHAS = (0.05, 0.1, 0.2, 0.4, 0.8)


def regions(truth: np.ndarray, spacing: tuple[float, float, float]) -> dict[str, np.ndarray]:
    """Boolean masks of the regions of a scene (shape of ``truth``), from the truth's objects (Δn > SUPPORT_DN)."""
    obj = truth > SUPPORT_DN
    pad = np.pad(obj, 1, mode="edge")
    c = pad[1:-1, 1:-1, 1:-1]
    lateral_out = ~(pad[1:-1, :-2, 1:-1] & pad[1:-1, 2:, 1:-1] & pad[1:-1, 1:-1, :-2] & pad[1:-1, 1:-1, 2:])
    axial_out = ~(pad[:-2, 1:-1, 1:-1] & pad[2:, 1:-1, 1:-1])
    edge = c & lateral_out
    cap = c & ~lateral_out & axial_out
    interior = obj & ~edge & ~cap
    dist = ndimage.distance_transform_edt(~obj, sampling=spacing)
    near = ~obj & (dist <= NEAR_UM)
    return {"interior": interior, "lateral_edge": edge, "axial_cap": cap, "near_background": near, "far_background": ~obj & ~near}


def _neigh_max(a: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    return neighbourhood_max(a, size[0], size[1])


def scores(result: np.ndarray, reps: np.ndarray, kind: str, size: tuple[int, int], alpha: float) -> np.ndarray:
    """The raw score ``kind`` (module docstring) of one scene; float64, the volume's shape. The bootstrap's kinds are
    the product's :func:`napari_fdt.recon.assess.bounds.raw_score`; ``reps`` holds the two half-set volumes for
    ``halves``."""
    if kind == "constant":
        return np.ones_like(result, dtype=np.float64)
    if kind == "contrast":
        return _neigh_max(np.abs(result), size) + 1e-4
    if kind == "spread":
        return _neigh_max(reps.std(axis=0, ddof=1), size) + 1e-6
    if kind == "halves":
        return _neigh_max(np.abs(reps[0] - reps[1]), size) + 1e-6
    return raw_score(result, reps, slices=size[0], pixels=size[1], alpha=alpha, deflate=kind.startswith("deflated"))


KINDS = {"constant": [((1, 1), 0.0)], "contrast": [(s, 0.0) for s in SIZES], "spread": [(s, 0.0) for s in SIZES],
         "bias+spread": [(s, 0.0) for s in SIZES], "bias+spread+contrast": [(s, a) for s in SIZES for a in ALPHAS],
         "deflated": [(s, 0.0) for s in SIZES], "deflated+contrast": [(s, a) for s in SIZES for a in ALPHAS],
         "halves": [(s, 0.0) for s in SIZES]}
#: controls, reported but never shipped
CONTROLS = ("halves",)


class Scene:
    def __init__(self, row: dict):
        self.name, self.family, self.seed, self.sites = row["scene"], row["family"], row["seed"], row["sites"]
        arrays = np.load(OUT / self.name / "arrays.npz")
        self.truth, self.result, self.reps = arrays["truth"], arrays["result"], arrays["replicates"]
        self.halves = arrays["halves"] if "halves" in arrays.files else None
        o = _optics(self.family)
        self.regions = regions(self.truth, (o.slice_spacing_um, o.pixel_size_um, o.pixel_size_um))
        self.error = np.abs(self.result - self.truth).astype(np.float64)
        self.support = (np.abs(self.truth) > SUPPORT_DN) | (np.abs(self.result) > SUPPORT_DN)

    def inputs(self, kind: str) -> np.ndarray:
        """The volumes the score ``kind`` reads: the two halves for ``halves``, else the replicates."""
        return self.halves if kind == "halves" else self.reps


def evaluate(scenes: list[Scene], kind: str, size, alpha, q: float) -> dict:
    """Coverage over the support, per region, width ratio and planted-bead calls of U = q·S on ``scenes``."""
    cover, width, err = [], 0.0, 0.0
    per_region = {r: [0, 0] for r in scenes[0].regions}
    per_scene, empty_calls, planted = [], [], []
    for sc in scenes:
        u = q * scores(sc.result, sc.inputs(kind), kind, size, alpha)
        ok = sc.error <= u
        sup = sc.support
        cover.append(ok[sup])
        per_scene.append(float(ok[sup].mean()))
        width += float(u[sup].sum())
        err += float(sc.error[sup].sum())
        for r, m in sc.regions.items():
            per_region[r][0] += int((ok & m & sup).sum())
            per_region[r][1] += int((m & sup).sum())
        for s in sc.sites:
            k, i, j = s["voxel"]
            call = bool(sc.result[k, i, j] - u[k, i, j] > 0)
            (planted if s["delta_n"] > 0 else empty_calls).append((call, s["delta_n"], s["kind"]))
    allc = np.concatenate(cover)
    out = {"coverage": float(allc.mean()), "coverage_scene_min": min(per_scene), "coverage_scene_max": max(per_scene),
           "width_ratio": width / err,
           "regions": {r: (a / b if b else None) for r, (a, b) in per_region.items()},
           "region_voxels": {r: b for r, (a, b) in per_region.items()},
           "false_calls": sum(c for c, _, _ in empty_calls) / max(1, len(empty_calls)), "empty_sites": len(empty_calls)}
    bins = ((0.002, 0.005), (0.005, 0.01), (0.01, 0.02))
    out["sensitivity"] = {f"{a:g}-{b:g}": (sum(c for c, d, _ in planted if a <= d < b) / max(1, sum(1 for _, d, _ in planted if a <= d < b)),
                                           sum(1 for _, d, _ in planted if a <= d < b)) for a, b in bins}
    return out


def calibrate(scenes: list[Scene], kind: str) -> tuple[tuple, float, float]:
    """(size, alpha), q and the calibration width ratio of ``kind``'s setting narrowest on ``scenes``."""
    best = None
    for size, alpha in KINDS[kind]:
        ratios = np.concatenate([(sc.error / scores(sc.result, sc.inputs(kind), kind, size, alpha))[sc.support] for sc in scenes])
        q = conformal_quantile(ratios, LEVEL)
        width = sum(float((q * scores(sc.result, sc.inputs(kind), kind, size, alpha))[sc.support].sum()) for sc in scenes)
        width /= sum(float(sc.error[sc.support].sum()) for sc in scenes)
        if best is None or width < best[2]:
            best = ((size, alpha), q, width)
    return best


def select(cal: list[Scene]) -> tuple[str, dict]:
    """The score to ship, chosen on the calibration scenes alone: for each kind, each family in turn is left out of
    the calibration scenes, the kind calibrated on the others and tested on it; the kind whose worst left-out coverage
    is highest wins (ties within 0.01: the narrower mean width; the controls are measured, never chosen). Returns the
    kind and each kind's figures."""
    figures = {}
    for kind in [k for k in KINDS if k not in CONTROLS or all(s.halves is not None for s in cal)]:
        covers, widths = [], []
        for fam in sorted({s.family for s in cal}):
            inner = [s for s in cal if s.family != fam]
            (size, alpha), q, _ = calibrate(inner, kind)
            ev = evaluate([s for s in cal if s.family == fam], kind, size, alpha, q)
            covers.append(ev["coverage"])
            widths.append(ev["width_ratio"])
        figures[kind] = {"worst_left_out_coverage": min(covers), "mean_left_out_width": float(np.mean(widths))}
    best = max([k for k in figures if k not in CONTROLS], key=lambda k: (round(figures[k]["worst_left_out_coverage"], 2), -figures[k]["mean_left_out_width"]))
    return best, figures


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="error_bounds table")
    p.add_argument("--write", action="store_true", help="also write the table to benchmarks/results/error_bounds_table_cpu.json")
    args = p.parse_args(argv)
    rows = {r["scene"]: r for r in read_rows(RESULTS) if (OUT / r["scene"] / "arrays.npz").exists()}
    scenes = [Scene(r) for r in rows.values()]
    print(f"{len(scenes)} scenes: " + ", ".join(f"{f} {sum(s.family == f for s in scenes)}" for f in FAMILIES))
    tables = {}
    cal_all = [s for s in scenes if s.seed % 2 == 0]
    chosen, figures = select(cal_all)
    print("\n## choice of the score on the calibration scenes alone (each family left out of them in turn)")
    for kind, f in figures.items():
        print(f"{kind:<22} worst left-out coverage {f['worst_left_out_coverage']:.3f}, mean width {f['mean_left_out_width']:.2f}"
              + ("  <- shipped" if kind == chosen else ""))
    (size, alpha), q, w = calibrate(cal_all, chosen)
    print(f"shipped: {chosen}, {size[0]} slices x {size[1]} px, alpha {alpha:g}, q {q:.6g} "
          f"(calibrated on {len(cal_all)} scenes; calibration width {w:.2f})")
    tables["choice"] = {"kind": chosen, "figures": figures, "slices": size[0], "pixels": size[1], "alpha": alpha, "q": q,
                        "scenes": len(cal_all)}
    ev = evaluate([s for s in scenes if s.seed % 2 == 1], chosen, size, alpha, q)
    print(f"planted faint beads on the test scenes: false 'supported' calls {ev['false_calls']:.2f} of {ev['empty_sites']} "
          "empty sites; sensitivity by Δn: " + ", ".join(f"{k}: {v[0]:.2f} of {v[1]}" for k, v in ev["sensitivity"].items()))
    splits = {"all families": None, **{f"{f} left out": f for f in FAMILIES}}
    for split, left in splits.items():
        cal = [s for s in scenes if s.family != left and s.seed % 2 == 0]
        test = [s for s in scenes if s.family != left and s.seed % 2 == 1]
        out_family = [s for s in scenes if s.family == left]
        if not cal or not test:
            continue
        print(f"\n## {split}: calibrate on {len(cal)} scenes, test on {len(test)}" + (f" and {len(out_family)} of {left}" if left else ""))
        print(f"{'score':<22} {'setting':<16} {'q':>8} {'cal w':>6} | {'cover':>5} {'min':>5} {'width':>5} "
              f"{'inter':>5} {'edge':>5} {'cap':>5} {'near':>5} {'far':>5} {'false':>5}" + (" | left-out cover, width" if left else ""))
        have_halves = all(s.halves is not None for s in scenes)
        for kind in [k for k in KINDS if have_halves or k not in CONTROLS]:
            (size, alpha), q, w = calibrate(cal, kind)
            ev = evaluate(test, kind, size, alpha, q)
            reg = ev["regions"]
            line = (f"{kind:<22} {str(size) + (f' a{alpha:g}' if alpha else ''):<16} {q:8.3g} {w:6.2f} | {ev['coverage']:.3f} "
                    f"{ev['coverage_scene_min']:.2f} {ev['width_ratio']:5.2f} "
                    + " ".join(f"{reg[r]:.3f}" if reg[r] is not None else "  -  " for r in
                               ("interior", "lateral_edge", "axial_cap", "near_background", "far_background"))
                    + f" {ev['false_calls']:.2f}")
            entry = {"setting": {"size": size, "alpha": alpha}, "q": q, "calibration_width_ratio": w, "test": ev}
            if left:
                lo = evaluate(out_family, kind, size, alpha, q)
                line += f" | {lo['coverage']:.3f}, {lo['width_ratio']:.2f}"
                entry["left_out"] = lo
            print(line)
            tables.setdefault(split, {})[kind] = entry
    if args.write:
        write_document(results_file("error_bounds_table", table=False), {"tables": tables})
    return 0
