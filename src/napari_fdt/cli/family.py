"""``fdt reconstruct --tv-family``: a family of volumes across TV weights (:mod:`napari_fdt.recon.run.family`), written as
each member completes (``RI_tv3.tif`` beside ``--out``), then the pick to ``--out`` with the family's verdict in its
report (``regularisation.family``)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from napari_fdt.errors import FDTInputError
from napari_fdt.recon.settings.config import AUTO, SolverConfig

__all__ = ["member_path", "family_on", "check_family_request", "run_family_and_write", "planned_config", "family_summary",
           "family_json"]


def family_on(config: SolverConfig, args: Any, distributed_launch: bool = False) -> bool:
    """Whether ``fdt reconstruct`` (and ``fdt plan``) make a family: ``tv_family`` "true" (then
    :func:`check_family_request` refuses what a family cannot do), "false" never; "auto" on a CUDA device where nothing
    the command asks for excludes a family (TV weights as numbers, ``--resume`` of one run's checkpoints,
    ``half_set_resolution``, ``error_bounds``) and not under torchrun (a launch sized for one run; ``--tv-family`` runs
    the family there), and never on the CPU, where a family costs 2.3x a run (median; docs/decisions/tv-family.md,
    "Default, per device"). ``--resume`` of a family's checkpoint folder resumes the family, whatever the settings say
    (a resumed run takes its checkpoint's settings)."""
    if _family_folder(args):
        return True
    if config.tv_family != AUTO:
        return config.tv_family == "true"
    from napari_fdt.device import resolve_device

    if resolve_device(getattr(args, "device", None) or "auto").type != "cuda":
        return False
    return not config.error_bounds and not distributed_launch and _excluded(config, args) is None


def _excluded(config: SolverConfig, args: Any) -> FDTInputError | None:
    """What the command asks for that a family cannot do, as the error :func:`check_family_request` raises (the first
    of them), or None. (``error_bounds`` with a family is refused by ``cli/bounds.check_bounds_request``.)"""
    if config.tv_xy_weight != AUTO or config.tv_z_weight != AUTO:
        return FDTInputError("tv_family", "sets the TV weights of its members itself, but tv_xy_weight or tv_z_weight is a number",
                             'leave both "auto" with --tv-family, or give the weights without it')
    if getattr(args, "resume", None) is not None and not _family_folder(args):
        return FDTInputError("tv_family", f"cannot resume from {args.resume}: it holds one run's checkpoints, not a "
                             "family's (a family's folder holds family.json and a tv<weight> folder per member)",
                             "resume that run without --tv-family (its own settings), or point --resume at the folder a "
                             "family wrote with --checkpoint-dir")
    if config.half_set_resolution:
        return FDTInputError("tv_family", "and half_set_resolution together would run six more half runs",
                             "run the family, then the picked member's report with --config RI.json --half-set-resolution")
    return None


def _family_marker(args: Any) -> tuple[SolverConfig, tuple[float, ...]] | None:
    """The settings and weights of the family whose checkpoint folder ``--resume`` names
    (:func:`~napari_fdt.recon.run.family.read_family_marker`), or None where it names none."""
    from napari_fdt.recon.run.family import read_family_marker

    resume = getattr(args, "resume", None)
    return read_family_marker(resume) if resume is not None and Path(resume).is_dir() else None


def _family_folder(args: Any) -> bool:
    """Whether ``--resume`` names a family's checkpoint folder (:data:`~napari_fdt.recon.run.family.FAMILY_MARKER`)."""
    return _family_marker(args) is not None


def member_path(out: Path, tau: float) -> Path:
    """Where member ``tau`` goes beside ``out``: ``RI.tif`` → ``RI_tv3.tif`` (``RI.ome.zarr`` → ``RI_tv3.ome.zarr``)."""
    from napari_fdt.data.io import beside

    return beside(out, f"tv{tau:g}")


def planned_config(config: SolverConfig, family: bool) -> SolverConfig:
    """The configuration one run of ``config`` plans: with a ``family`` (:func:`family_on`), a member's (every member
    plans alike: the TV weights are numbers and no trials run)."""
    from napari_fdt.recon.run.family import FAMILY_TAUS, member_config

    return member_config(config, FAMILY_TAUS[0]) if family else config


def family_summary(family: bool, plan) -> str:
    """``fdt plan``'s text: the plan, or with a ``family`` the family's price and one member's plan."""
    from napari_fdt.recon.loop.plan import seconds_in_words
    from napari_fdt.recon.run.family import FAMILY_TAUS

    if not family:
        return plan.summary()
    n = len(FAMILY_TAUS)
    most = (f" where the data ask for no model part, up to about {seconds_in_words(n * plan.most_s)} where they ask for the costliest"
            " (a member that shares the first one's parts runs no tests)" if plan.most_s and plan.if_part_kept_s else "")
    return (f"a family of {n} volumes, one whole run per TV weight (τ_xy {', '.join(f'{t:g}' for t in FAMILY_TAUS)}): "
            f"about {seconds_in_words(n * plan.predicted_s)} in all{most}; each member's plan:\n{plan.summary()}")


def family_json(family: bool, plan) -> dict[str, Any]:
    """``fdt plan --json``'s ``tv_family`` entry (empty without a ``family``)."""
    from napari_fdt.recon.run.family import FAMILY_TAUS

    if not family:
        return {}
    n = len(FAMILY_TAUS)
    return {"tv_family": {"taus": list(FAMILY_TAUS), "predicted_member_s": plan.predicted_s,
                          "predicted_total_s": n * plan.predicted_s,
                          "predicted_total_s_if_the_costliest_parts_are_kept": n * plan.most_s if plan.most_s else None}}


def check_family_request(config: SolverConfig, args: Any, out: Path) -> list[Path]:
    """Refuse what a family cannot do, before any run (FDTInputError naming the field); return the members' paths
    (each checked free unless ``--overwrite``)."""
    from napari_fdt.data.io import report_path
    from napari_fdt.recon.run.family import FAMILY_TAUS

    excluded = _excluded(config, args)
    if excluded is not None:
        raise excluded
    marker = _family_marker(args)
    paths = [member_path(out, tau) for tau in (FAMILY_TAUS if marker is None else marker[1])]
    for p in paths:
        for q in (p, report_path(p)):
            if q.exists() and not args.overwrite and marker is None:  # (resumed: the members written before)
                raise FDTInputError("out", f"{q} (a member of the family) exists", "choose another --out or pass --overwrite")
    return paths


def run_family_and_write(args, config: SolverConfig, acq, out: Path, truth, truth_src, group=None) -> int:
    """Run the family (the request checked by :func:`check_family_request`), each member written as it completes, then
    the pick to ``out``; prints the verdict. ``group``: this rank's under torchrun (every rank runs the members; rank 0
    alone writes and prints)."""
    from napari_fdt.cli.progress import _progress_bar, _show_progress
    from napari_fdt.data.io import report_path
    from napari_fdt.recon.loop.checkpoint import has_checkpoint
    from napari_fdt.recon.run.family import FAMILY_TAUS, Member, family_entries, member_config, member_folder, run_family, with_family
    from napari_fdt.recon.run.report import write_result
    from napari_fdt.recon.run.session import finish_run
    from napari_fdt.recon.run.solver import Reconstructor

    marker, taus, sources = _family_marker(args), FAMILY_TAUS, None
    resume, writer = marker is not None, group is None or group.is_writer
    device = args.device if group is None else group.device
    if resume:  # the family's own settings and weights; each member from its checkpoint where it left one
        config, taus = marker
        done = [f"τ_xy {t:g}" for t in taus if has_checkpoint(member_folder(args.resume, t))]
        if writer:
            print(f"resuming the family in {args.resume} (checkpoints of {', '.join(done) or 'no member yet'})", file=sys.stderr)
    else:
        first = Reconstructor(acq, member_config(config, taus[0]), device=device, group=group)
        sources = first.initial_sources_um
        if writer:
            print(family_summary(True, first.plan), file=sys.stderr)
    checkpoint_dir = args.checkpoint_dir if args.checkpoint_dir is not None else args.resume if resume else None
    paths = [member_path(out, tau) for tau in taus]  # (as check_family_request found them free)
    reports: dict[float, dict[str, Any]] = {}

    def keep(member: Member) -> None:
        if not writer:
            return
        path = paths[taus.index(member.tau)]
        report = finish_run(member.rec, False, output=str(path), acquisition_path=str(args.acquisition), truth_ri=truth,
                            truth_sources_um=truth_src)
        reports[member.tau] = report
        write_result(member.rec, path, report, overwrite=args.overwrite)
        err = f"held-out error {member.validation_error:.4f}" if member.validation_error is not None else "no held-out images"
        print(f"member τ_xy {member.tau:g} done ({member.seconds:.0f} s, {err}): wrote {path}", file=sys.stderr)

    bar, current = None, -1
    runs = run_family(acq, config, device=device, initial_sources_um=sources, keep=keep, taus=taus,
                      checkpoint_dir=checkpoint_dir, resume=resume, group=group)
    try:
        while True:
            try:
                k, snap = next(runs)
            except StopIteration as stop:
                family = stop.value
                break
            if k != current:
                if bar is not None:
                    bar.close()
                bar, current = _progress_bar(snap.plan_iterations, disable=args.quiet or not writer), k
                if writer:
                    print(f"member {k + 1}/{len(taus)}: τ_xy {taus[k]:g}", file=sys.stderr)
            _show_progress(bar, snap)
    except KeyboardInterrupt:
        runs.close()
        if not writer:
            return 130
        again = f"; --resume {checkpoint_dir} continues it" if checkpoint_dir is not None else ""
        print(f"interrupted: {len(reports)} member(s) complete and written; no pick{again}", file=sys.stderr)
        return 130
    finally:
        if bar is not None:
            bar.close()
    if not writer:
        return 0
    chosen = family.chosen
    entries = family_entries(family, reports, [str(out if m.picked else p) for m, p in zip(family.members, paths)])
    report = with_family({**reports[chosen.tau], "output": str(out)}, entries, chosen.tau, family.reason)
    write_result(chosen.rec, out, report, overwrite=args.overwrite)
    picked = paths[family.pick]
    for q in (picked, report_path(picked)):  # the pick lives at --out now
        if q.is_dir():
            import shutil

            shutil.rmtree(q)
        elif q.exists():
            q.unlink()
    print(describe_family(entries, family.reason))
    print(f"wrote {out} and {report_path(out)} (the pick, τ_xy {chosen.tau:g}); the other members beside it")
    return 0


def describe_family(entries: list[dict[str, Any]], reason: str) -> str:
    """The verdict in words: one line per member (smoother / sharper, held-out error, its difference to the best with
    its standard error, whether the images tell it apart)."""
    lines = ["TV family (held-out error; mean paired difference to the best member ± its standard error):"]
    for e in entries:
        if e["validation_error"] is None:
            lines.append(f"  τ_xy {e['tau']:g}: no held-out images")
            continue
        diff = e["mean_difference_to_best"]
        se = e["standard_error"]
        tell = "the images cannot tell it from the best" if e["indistinguishable_from_best"] else "worse than the best"
        dn = f", Δn error {e['relative_delta_n_error']:.3f}" if "relative_delta_n_error" in e else ""
        lines.append(f"  τ_xy {e['tau']:g}{' (picked)' if e['picked'] else ''}: {e['validation_error']:.4f}, "
                     f"{diff:+.4f}" + (f" ± {se:.4f}" if se is not None else "") + f" ({tell}){dn}")
    lines.append(f"  pick: {reason}; larger weights are smoother, smaller ones sharper")
    return "\n".join(lines)
