"""The result of a reconstruction: the RI volume on disk (OME-TIFF) and its report (``RI.json``).

The report holds everything needed to judge and reproduce the result: the configuration, the package
version, the calibrated sources and optical parameters, per-stage grid size, iterations and seconds
per iteration, the final loss terms, the fit of all images, and metrics against the truth when given.
"""

from __future__ import annotations

import datetime as _dt
import platform
from pathlib import Path
from typing import Any

import numpy as np
import torch

from napari_fdt.data.io import check_report_free, report_path, write_json_atomic
from napari_fdt.data.volumes import write_volume
from napari_fdt.model.render import iter_batches
from napari_fdt.recon.assess.fsc import TRUTH_THRESHOLD, resolutions
from napari_fdt.recon.assess.metrics import image_metrics, ri_metrics
from napari_fdt.recon.run.solver import Reconstructor

__all__ = ["evaluate_images", "plan_report", "describe_plan", "build_report", "write_result", "source_errors"]


def evaluate_images(rec: Reconstructor, batch_size: int | None = None) -> tuple[np.ndarray, dict[str, float]]:
    """Predict every image with the final state on the acquisition grid; return (predictions (N, H, W), metrics).

    Predictions are in the acquisition's intensity units (calibrated gains applied).
    """
    acq = rec.acquisition
    stage = rec.evaluation_stage()
    preds = np.empty(acq.images.shape, dtype=np.float32)
    bs = batch_size or rec.config.batch_size
    for sl in iter_batches(acq.n_images, bs):
        preds[sl] = rec.predict(np.arange(sl.start, sl.stop), stage)
    return preds, image_metrics(preds, acq.images)


def source_errors(calibrated_um: np.ndarray, true_um: np.ndarray) -> dict[str, float]:
    """RMS lateral and depth errors (µm) of calibrated source positions against the truth."""
    d = np.asarray(calibrated_um) - np.asarray(true_um)
    return {
        "lateral_rms_um": float(np.sqrt(np.mean(np.sum(d[:, :2] ** 2, axis=1)))),
        "depth_rms_um": float(np.sqrt(np.mean(d[:, 2] ** 2))),
    }


def stage_lengths(rec: Reconstructor) -> dict[str, Any]:
    """The stages' iterations as asked (``requested_iterations``) and as run (``iterations``), and the passes over
    the images each makes (iterations × batch / images; a source is fitted once per pass): the finest stage is
    lengthened to ``final_stage_min_passes`` (:func:`napari_fdt.recon.settings.config.resolve_stage_lengths`)."""
    cfg = rec.config
    n = max(1, rec.acquisition.n_images)
    used = [s.iterations for s in cfg.stages]
    asked = rec.requested_config.stages
    return {"requested_iterations": [s.iterations for s in asked], "iterations": used,
            "passes": [s.iterations * min(cfg.stage_batch(i), n) / n for i, s in enumerate(cfg.stages)],
            "final_stage_min_passes": cfg.final_stage_min_passes, "n_images": n}


def plan_report(rec) -> dict[str, Any]:
    """The run's plan (:mod:`napari_fdt.recon.loop.plan`) with each phase's measured seconds (None: not reached): the
    report's time table."""
    plan = rec.plan.to_dict()
    for phase, seconds in zip(plan["phases"], rec.pace.measured_seconds()):
        phase["seconds"] = seconds
    return plan


def describe_plan(plan: dict[str, Any]) -> str:
    """The time table in one line: each phase's measured seconds (and the plan's prediction)."""
    cells = [f"{p['name']} {p['seconds']:.1f} s (~{p['predicted_s']:.0f})" for p in plan["phases"] if p.get("seconds") is not None]
    return "time by phase (s, predicted): " + "; ".join(cells)


def build_report(
    rec: Reconstructor,
    *,
    output: str | None = None,
    acquisition_path: str | None = None,
    truth_ri: np.ndarray | None = None,
    truth_sources_um: np.ndarray | None = None,
    cancelled: bool = False,
    evaluate: bool = True,
) -> dict[str, Any]:
    """The content of ``RI.json`` for the current state of ``rec``."""
    from napari_fdt._version import __version__

    o = rec.acquisition.optics
    src = rec.sources_um()
    report: dict[str, Any] = {
        "format": "napari-fdt-report",
        "version": 1,
        "napari_fdt_version": __version__,
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "acquisition": acquisition_path,
        "output": output,
        "cancelled": cancelled,
        "completed_stages": rec.completed_stages,
        "n_stages": len(rec.config.stages),
        "device": str(rec.device),
        "hardware": {"torch": torch.__version__, "python": platform.python_version(), "threads": torch.get_num_threads(),
                     "device_name": torch.cuda.get_device_name(rec.device) if rec.device.type == "cuda" else platform.processor() or platform.machine()},
        "config": rec.requested_config.to_dict(),  # as given; the stages as run: stage_lengths
        "stage_lengths": stage_lengths(rec),
        "ri": {"shape": [o.n_slices, *rec.full_shape], "n_background": o.n_background, "units": "absolute refractive index",
               "voxel_size_um": [o.slice_spacing_um, o.pixel_size_um, o.pixel_size_um],
               "slice_order": "slice 0 nearest the sources"},
        "calibration": {
            **rec.calibration.summary(),
            "sources_um": src.tolist(),
            "initial_sources_um": rec.initial_sources_um.tolist(),
            "gains": rec.gains().tolist(),
        },
        "stages": [r.to_dict() for r in rec.stages],
        "regularisation": {"tv_xy_weight": rec.loss_weights.tv_xy, "tv_z_weight": rec.loss_weights.tv_z,
                           "chosen": None if rec.tv_choice is None else rec.tv_choice.to_dict()},
        "model_parts": model_parts_summary(rec),
        "seconds_total": rec.elapsed_s,
        "plan": plan_report(rec),
        "history": rec.history,
        "final_losses": rec.final_losses,
    }
    if rec.group is not None:
        report["distributed"] = rec.group.describe()
    if evaluate and rec.volume is not None:
        _, report["image_fit"] = evaluate_images(rec)
    held = rec.validation_indices
    if len(held) and rec.stages and rec.stages[-1].validation_error is not None:
        # the last stage's held-out error: how well the volume predicts images it was not fitted to
        report["validation"] = {"error": rec.stages[-1].validation_error, "n_images": int(len(held)), "indices": [int(i) for i in held],
                                "best_iteration": rec.stages[-1].best_iteration, "early_stopping": rec.config.early_stopping}
    metrics: dict[str, Any] = {}
    if truth_ri is not None and rec.volume is not None:
        metrics.update(ri_metrics(rec.ri_full(), truth_ri, o.n_background))
        # the resolution the truth gives (FSC 0.5): what the half-set figure (``resolution``) is checked against
        found = resolutions(rec.delta_n_full(), np.asarray(truth_ri, dtype=np.float64) - o.n_background, o.pixel_size_um,
                            o.slice_spacing_um, TRUTH_THRESHOLD)
        metrics["resolution_against_truth"] = {d: r.to_dict() for d, r in found.items()}
    if truth_sources_um is not None:
        metrics["sources"] = source_errors(src, truth_sources_um)
        metrics["sources_initial"] = source_errors(rec.initial_sources_um, truth_sources_um)
    if metrics:
        report["metrics"] = metrics
    return report


def model_parts_summary(rec: Reconstructor) -> dict[str, Any]:
    """RI.json's ``model_parts``: each optional part of the model on or off and why (:mod:`napari_fdt.recon.loop.model_parts`),
    ``needed`` (the parts on), and the choice's trials and cost when the data chose (``chosen``; None before)."""
    choice = rec.parts_choice
    return {"parts": dict(rec.parts), "needed": [p for p, on in rec.parts.items() if on],
            "chosen_by": None if choice is None else dict(choice.chosen_by),
            "chosen": None if choice is None or not choice.trials else choice.to_dict()}


def describe_parts(summary: dict[str, Any]) -> str:
    """One line for people: which parts the scene needed, by what, and what the choice cost (CLI and widget)."""
    chosen = summary.get("chosen")
    needed = ", ".join(summary.get("needed") or []) or "none"
    if not chosen:
        return f"model parts on: {needed}"
    again = {"stages": "again, all stages rerun", "finest": "again, finest stage rerun", "before": ""}

    def when(t: dict[str, Any]) -> str:
        said = [again[t.get("after", "stages")]] if t.get("pass", 1) > 1 else []
        said += [f"at stage {t['at_stage'] + 1}'s end"] if "at_stage" in t else []
        said += ["before the stages, at Δn = 0"] if t.get("pass", 1) == 0 else []
        said += [f"by {t['iterations']} iterations of training with it and without"] if t.get("test") == "branch" else []
        said += [f"tried before keeping the {t['before_part']} model"] if t.get("before_part") else []
        said += ["set aside: the 2x field grid tried first"] if t.get("waits_for") == "field_grid" else []
        said = [w for w in said if w]
        return f" ({', '.join(said)})" if said else ""

    def base(t: dict[str, Any]) -> float:  # the error the change is relative to (a branch's: its arm without the part)
        return max(t.get("validation_error_without") or t.get("reference_error") or chosen["reference_error"] or 1e-30, 1e-30)

    tried = ", ".join(f"{t['part']}{when(t)} {'on' if t['on'] else 'off'} ({-100 * t.get('improvement', 0.0) / base(t):+.1f} %)"
                      for t in chosen["trials"] if "improvement" in t)
    shared = [t for t in chosen["trials"] if "shared_from" in t]  # a family member's start (recon/run/family.py)
    said = (f"; {', '.join(t['part'] for t in shared)} on from the first stage, as the family's τ {shared[0]['shared_from']:g} "
            "member kept them") if shared else ""
    if chosen["reference_error"] is None:
        return f"model parts on: {needed}{said}" + _describe_backward(chosen.get("backward"))
    where = f"in stage {chosen['stage'] + 1}" if chosen["stage"] >= 0 else "before the stages"
    return (f"model parts on: {needed} (chosen by the validation error {chosen['reference_error']:.4f} {where}, "
            f"{chosen['seconds']:.1f} s; change of the held-out error with each part: {tried}{said})" + _describe_backward(chosen.get("backward")))


def _describe_backward(backward: dict[str, Any] | None) -> str:
    """The backward step's words (:mod:`napari_fdt.recon.choices.parts_backward`): each kept part's effect in the final state."""
    if not backward or not backward.get("effects"):
        return ""

    def effect(e: dict[str, Any]) -> str:
        z = e["improvement"] / e["standard_error"] if e.get("standard_error") else float("nan")
        return (f"{e['part']} {'kept' if e['earns'] else 'dropped'} (held-out error {100 * e['improvement'] / backward['reference_error']:+.1f} % "
                f"without it, {z:.1f} SE)")

    said = "; at the end, in the final state: " + ", ".join(effect(e) for e in backward["effects"])
    rerun = backward.get("rerun")
    if rerun is not None:
        said += (", the finest stage ran again without the dropped parts and was kept" if rerun["keep_rerun"] else
                 ", the finest stage ran again without them, was worse by more than noise, and the run went back to them")
    return said


def write_result(rec: Reconstructor, out: str | Path, report: dict[str, Any], *, overwrite: bool = False) -> tuple[Path, Path]:
    """Write ``out`` (OME-TIFF, or OME-Zarr for a ``.zarr`` name; absolute RI, float32, ZYX) and ``out``'s ``.json`` report, each atomically."""
    out = Path(out)
    o = rec.acquisition.optics
    json_path = report_path(out)
    check_report_free(out)  # RI.tif and RI.ome.tif share RI.json: never replace another volume's report
    write_volume(out, rec.ri_full(), (o.slice_spacing_um, o.pixel_size_um, o.pixel_size_um), overwrite=overwrite)
    write_json_atomic(json_path, report, overwrite=overwrite)
    return out, json_path
