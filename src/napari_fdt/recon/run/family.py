"""A family of volumes across TV weights (``tv_family``): each member a whole run at one weight, and the data's verdict.

Where the images do not constrain the volume (the missing cone), the smoothing decides what it holds, and no signal
cheaper than each weight's whole path ranks the weights (docs/decisions/tv-half-sets.md, sections 1-6): the held-out
images rank them once each weight has shaped the whole run (section 4). So the family runs each member's whole path, a
run whose TV weights are the member's numbers (the same as ``fdt reconstruct --tv-xy-weight τ --tv-z-weight τ/2``:
every other choice, the model parts included, made by that run), and compares their held-out images at the end:

* each member's held-out error (:func:`~napari_fdt.recon.loop.run_validation.validation` at its finest stage), image by
  image, against the best member's: the mean paired difference and its standard error;
* members whose difference is within :data:`INDISTINGUISHABLE_SE` standard errors of the best's are ones the images
  cannot tell apart;
* the pick: the largest weight whose held-out error is within :data:`PICK_TOLERANCE` of the best member's (section 4:
  over 15 scene/seed pairs of whole runs at τ 1, 3, 10, 30, any tolerance from 3.4 % to 8.3 % ended within 10 % of the
  best fixed weight's Δn error on every pair; 5 % is in the middle) *and* that the images cannot tell from the best:
  where they do (a consistent rise, beyond :data:`INDISTINGUISHABLE_SE` standard errors), the data speak and are
  followed (cells_fine seed 1: τ 10 at +2.4 %, told apart, 1.41× the best member's Δn error; τ 3 the best;
  docs/decisions/tv-family.md).

The members share the acquisition and the initial source positions (a member's run would compute the same ones), and
the first member's choice of model parts:

* where it kept none, the later members run with the ``"auto"`` parts off (:func:`parts_off`), no tests, which is bit
  for bit their own run wherever their own tests would keep nothing too (a test that keeps nothing leaves the run as it
  was; on 28 of 28 members measured whose first member kept nothing, they kept nothing);
* where it kept some and ran every stage again with them (``rerun`` ``"stages"``: sub-slices by the branch, the 2x
  grid, ...), the later members start with those parts on from their first stage (:func:`start_with_shared_parts`:
  as a run whose pilot kept them, multi-slice coarse stages), not a first pass without them and its tests. A cold
  run's second pass also starts from the state before any stage, so such a member is bit for bit its own run wherever
  its own first pass would keep the same parts (a kept pupil or aberrations start from the first member's values,
  where a cold run starts from its own first pass's). The parts not kept are still tried at its finest stage's end,
  and the shared ones tested backward at its end, so a member whose data do not want a shared part drops it
  (docs/decisions/tv-family.md, "Sharing a kept choice"). Where the pilot kept the parts, or only the finest stage
  ran again, each member makes its own choice: there a member runs no first pass of its own to save.

The family replaces the TV weights' trials: its members' weights are numbers. Without held-out images there is no
verdict and the pick is the smallest weight (a warning says so).

With a checkpoint folder each member writes its own (``tv<τ>/stage_*.pt`` under it, as a run's ``--checkpoint-dir``)
beside :data:`FAMILY_MARKER` (the family's settings and weights, plain JSON); resumed from that folder, members with a
checkpoint continue from it (a member that had completed does no more iterations), the others start as they would have.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Generator

import numpy as np

from napari_fdt.errors import FDTInputError, FDTWarning
from napari_fdt.recon.loop.regularisation import TV_Z_RATIO
from napari_fdt.recon.settings.config import AUTO, BEFORE_SPECTRAL, SolverConfig

if TYPE_CHECKING:
    from napari_fdt.data.acquisition import Acquisition
    from napari_fdt.recon.loop.snapshot import Snapshot
    from napari_fdt.recon.problem.distributed import Group
    from napari_fdt.recon.run.solver import Reconstructor

__all__ = ["FAMILY_TAUS", "PICK_TOLERANCE", "INDISTINGUISHABLE_SE", "Member", "Family", "member_config", "parts_off", "verdict",
           "start_with_shared_parts", "shared_parts", "FAMILY_MARKER", "member_folder", "read_family_marker", "run_family", "family_entries", "with_family"]

#: The members' lateral TV weights τ_xy (τ_z = τ_xy · TV_Z_RATIO): they bracket the best fixed weights measured (τ 1 on
#: the sample and thick slabs, 3 on a cells-like scene, 10 on cells and sparse beads: docs/decisions/tv-half-sets.md).
FAMILY_TAUS: tuple[float, ...] = (1.0, 3.0, 10.0)
#: A larger weight is picked while its held-out error is at most this much above the best member's (relative).
PICK_TOLERANCE = 0.05
#: Paired standard errors within which a member's held-out error counts as indistinguishable from the best's.
INDISTINGUISHABLE_SE = 2.0


@dataclass
class Member:
    """One member: its weights, its solver (None once released), its held-out errors at the end and its seconds."""

    tau: float
    tv_xy_weight: float
    tv_z_weight: float
    rec: Reconstructor | None = None
    validation_error: float | None = None
    image_errors: list[float] = field(default_factory=list)
    seconds: float = 0.0
    #: the verdict (:func:`verdict`): mean paired difference to the best member's held-out errors, its standard error,
    #: whether the images cannot tell this member from the best, and whether it is the pick
    mean_difference: float | None = None
    standard_error: float | None = None
    indistinguishable: bool | None = None
    picked: bool = False
    #: the weight of the member whose choice of model parts this member started from (:func:`run_family`); None: its own
    parts_shared_from: float | None = None
    #: the parts on from the first stage because that member kept them (empty where it kept none)
    parts_shared: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """RI.json's ``regularisation.family`` entry (without ``path``, which the writer adds)."""
        return {"tau": self.tau, "tv_xy_weight": self.tv_xy_weight, "tv_z_weight": self.tv_z_weight,
                "validation_error": self.validation_error, "mean_difference_to_best": self.mean_difference,
                "standard_error": self.standard_error, "indistinguishable_from_best": self.indistinguishable,
                "picked": self.picked, "seconds": self.seconds, "parts_shared_from": self.parts_shared_from,
                "parts_shared": list(self.parts_shared)}


@dataclass
class Family:
    """The members (in the order of :data:`FAMILY_TAUS`), the index of the pick and why it was picked."""

    members: list[Member]
    pick: int
    reason: str

    @property
    def chosen(self) -> Member:
        return self.members[self.pick]


def member_config(config: SolverConfig, tau: float) -> SolverConfig:
    """``config`` as member ``tau``'s run: the TV weights the member's numbers, no family (``--config`` of its report
    reruns that member alone)."""
    return dataclasses.replace(config, tv_xy_weight=float(tau), tv_z_weight=float(TV_Z_RATIO * tau), tv_family="false")


def parts_off(config: SolverConfig) -> SolverConfig:
    """``config`` with every ``"auto"`` model part off (a choice that kept none, taken as settings: no tests)."""
    off = {"sub_slices": 1, "field_oversampling": 1, "obliquity_correction": "false", "coherence": "none",
           "calibrate_pupil": "false", "calibrate_aberrations": "false"}
    return dataclasses.replace(config, **{k: v for k, v in off.items() if getattr(config, k) in (AUTO, BEFORE_SPECTRAL)})


def start_with_shared_parts(rec: Reconstructor, first: Reconstructor) -> None:
    """Start the fresh run ``rec`` with the ``"auto"`` parts the completed run ``first`` kept (its final choice, after
    its backward test) on from the first stage, as a run whose pilot kept them starts
    (:func:`~napari_fdt.recon.choices.parts_pilot.start_with_parts`: multi-slice coarse stages under ``coarse_model``
    ``"auto"``, the other auto parts tried at the finest stage's end, the kept ones tested backward at the end); the
    pupil and aberrations from ``first``'s final values where it kept them. Where it kept none that ``rec`` may choose,
    or ``rec`` has started (resumed), ``rec`` is left as it was; :func:`shared_parts` says what was shared."""
    from napari_fdt.recon.calibration.calibration import PUPIL_PARAMETERS
    from napari_fdt.recon.choices.parts_backward import kept_auto_parts
    from napari_fdt.recon.choices.parts_pilot import PilotOutcome, start_with_parts
    from napari_fdt.recon.loop.phases import PUPIL_PILOT

    kept = [p for p in kept_auto_parts(first) if p in rec._auto_parts]
    if not kept or rec.parts_choice is not None or rec.completed_stages:
        return
    fitted = (first if {"pupil", "aberrations"} & set(kept) else rec).calibration.copy_values(PUPIL_PARAMETERS)
    start_with_parts(rec, PilotOutcome(kept, fitted))
    rec.parts_choice.trials = [{"part": p, "on": True, "pass": 0, "shared_from": float(first.config.tv_xy_weight)} for p in kept]
    # no pilot runs now (a choice is made): its phase leaves the plan
    rec._revise_plan(dataclasses.replace(rec.plan, phases=tuple(p for p in rec.plan.phases if p.pass_name != PUPIL_PILOT)))


def shared_parts(rec: Reconstructor) -> tuple[list[str], float | None]:
    """The parts ``rec`` started with because the family's first member kept them (:func:`start_with_shared_parts`),
    and that member's τ_xy (None where none were shared); read from its choice, so a resumed member says it too."""
    marked = [] if rec.parts_choice is None else [t for t in rec.parts_choice.trials if "shared_from" in t]
    return [t["part"] for t in marked], (marked[0]["shared_from"] if marked else None)


def verdict(members: list[Member], tolerance: float = PICK_TOLERANCE,
            indistinguishable_se: float = INDISTINGUISHABLE_SE) -> tuple[int, str]:
    """Fill each member's verdict against the best member's held-out errors; return (the pick's index, the reason).

    The best member has the lowest held-out error; each member's paired difference to it (same images) has a mean and
    a standard error; the pick is the largest weight within ``tolerance`` (relative) of the best error that the images
    cannot tell from the best (within ``indistinguishable_se`` standard errors)."""
    scored = [k for k, m in enumerate(members) if m.validation_error is not None and math.isfinite(m.validation_error)]
    if not scored:
        return 0, "no held-out images: the smallest weight"
    best = min(scored, key=lambda k: members[k].validation_error)
    ref = np.asarray(members[best].image_errors, dtype=np.float64)
    for k in scored:
        d = np.asarray(members[k].image_errors, dtype=np.float64) - ref
        members[k].mean_difference = float(d.mean()) if d.size else 0.0
        members[k].standard_error = float(d.std(ddof=1) / np.sqrt(d.size)) if d.size >= 2 else None
        se = members[k].standard_error
        members[k].indistinguishable = k == best or (se is not None and abs(members[k].mean_difference) <= indistinguishable_se * se)
    limit = members[best].validation_error * (1.0 + tolerance)
    pick = max((k for k in scored if members[k].validation_error <= limit and members[k].indistinguishable),
               key=lambda k: members[k].tau)
    reason = (f"the largest weight whose held-out error is within {tolerance:.0%} of the best member's "
              f"(τ_xy {members[best].tau:g}: {members[best].validation_error:.4f}) and that the images cannot tell from it")
    return pick, reason


#: The file that makes a checkpoint folder a family's: ``{"format", "taus", "config"}`` (JSON, read without running code).
FAMILY_MARKER = "family.json"
_MARKER_FORMAT = "napari-fdt tv family"


def member_folder(directory: str | Path, tau: float) -> Path:
    """Member ``tau``'s checkpoint folder in a family's ``directory``: ``tv3`` for τ 3."""
    return Path(directory) / f"tv{tau:g}"


def read_family_marker(directory: str | Path) -> tuple[SolverConfig, tuple[float, ...]] | None:
    """The family's settings and weights from ``directory``'s :data:`FAMILY_MARKER`; None where ``directory`` is not a
    family's checkpoint folder (a run's, or not a folder); FDTInputError where the marker cannot be read."""
    marker = Path(directory) / FAMILY_MARKER
    if not marker.is_file():
        return None
    try:
        state = json.loads(marker.read_text(encoding="utf-8"))
        if state.get("format") != _MARKER_FORMAT:
            raise ValueError(f"format {state.get('format')!r}")
        return SolverConfig.from_dict(state["config"]), tuple(float(t) for t in state["taus"])
    except Exception as exc:  # noqa: BLE001 (bad JSON, a missing key, settings this version does not know)
        raise FDTInputError("resume", f"{marker} cannot be read as a family's checkpoint folder: {exc}",
                            "point --resume at the folder a family wrote with --checkpoint-dir, or start the family again") from None


def _write_family_marker(directory: str | Path, config: SolverConfig, taus: tuple[float, ...]) -> None:
    from napari_fdt.data.io import write_json_atomic

    Path(directory).mkdir(parents=True, exist_ok=True)
    write_json_atomic(Path(directory) / FAMILY_MARKER, {"format": _MARKER_FORMAT, "taus": list(taus),
                                                        "config": config.to_dict()}, overwrite=True)


def _member_run(acquisition: Acquisition, cfg: SolverConfig, tau: float, device: Any, sources: np.ndarray | None,
                resume_dir: Path | None, group: Group | None) -> Reconstructor:
    """Member ``tau``'s solver: from its checkpoint in ``resume_dir`` where it has one (its own settings), else new."""
    from napari_fdt.recon.loop.checkpoint import has_checkpoint
    from napari_fdt.recon.run.solver import Reconstructor

    folder = None if resume_dir is None else member_folder(resume_dir, tau)
    if folder is None or not has_checkpoint(folder):
        return Reconstructor(acquisition, cfg, device=device, initial_sources_um=sources, group=group)
    rec = Reconstructor.from_checkpoint(folder, acquisition, device=device, group=group)
    if rec.config.tv_xy_weight != float(tau):
        raise FDTInputError("resume", f"{folder} holds a run at τ_xy {rec.config.tv_xy_weight:g}, not member τ_xy {tau:g}",
                            "resume the family from the folder it wrote, unchanged, or start it again")
    return rec


def _held_out_errors(rec: Reconstructor) -> tuple[float | None, list[float]]:
    """The held-out error and each held-out image's at the run's end, through its finest stage's model."""
    from napari_fdt.recon.loop.run_validation import validation

    if not len(rec.validation_indices):
        return None, []
    stage = rec._build_stage(len(rec.config.stages) - 1)
    out = validation(rec, stage, rec._loss_mask(stage), per_image=True)
    return (None, []) if out is None else (out[0], list(out[1]))


def run_family(acquisition: Acquisition, config: SolverConfig, *, device: Any = "auto",
               initial_sources_um: np.ndarray | None = None, should_stop: Callable[[], bool] | None = None,
               taus: tuple[float, ...] = FAMILY_TAUS, keep: Callable[[Member], None] | None = None,
               checkpoint_dir: str | Path | None = None, resume: bool = False, group: Group | None = None,
               ) -> Generator[tuple[int, Snapshot], None, Family | None]:
    """Run each member's whole path in turn, yielding ``(member index, snapshot)``; returns the :class:`Family` with its
    verdict, or None when stopped (``should_stop``) before the last member completed.

    ``keep(member)`` is called as each member completes (a front end writes or shows it then; members stream as they
    finish); the member's solver stays in ``member.rec``. ``checkpoint_dir``: each member's checkpoints go to its
    :func:`member_folder` there, with the family's :data:`FAMILY_MARKER`; ``resume``: members that left a checkpoint
    there continue from it (``config`` and ``taus`` then as :func:`read_family_marker` gives them). ``group``: under
    torchrun every rank runs this with its :class:`~napari_fdt.recon.problem.distributed.Group` (each member a
    distributed run; the held-out errors, the parts' choices and so the verdict are summed over the ranks, the same on
    all); only the writer writes checkpoints and the marker, and a front end writes the members on it alone."""
    from napari_fdt.recon.choices.parts_backward import kept_auto_parts

    members: list[Member] = []
    sources, shared_from, first = initial_sources_um, None, None
    writer = group is None or group.is_writer
    if writer and checkpoint_dir is not None and not (resume and (Path(checkpoint_dir) / FAMILY_MARKER).is_file()):
        _write_family_marker(checkpoint_dir, config, taus)
    for k, tau in enumerate(taus):
        cfg = member_config(config, tau) if shared_from is None else parts_off(member_config(config, tau))
        t0 = time.perf_counter()
        rec = _member_run(acquisition, cfg, tau, device, sources, Path(checkpoint_dir) if resume and checkpoint_dir else None, group)
        before_s = rec.elapsed_s  # a resumed member's seconds before this process
        sources = rec.initial_sources_um  # the first member's start (fitted once where the acquisition gives none)
        if first is not None:
            start_with_shared_parts(rec, first)
        folder = None if checkpoint_dir is None else member_folder(checkpoint_dir, tau)
        for snap in rec.run(should_stop=should_stop, checkpoint_dir=folder):
            yield k, snap
        if rec.completed_stages < len(cfg.stages):
            return None
        shared, kept_by = shared_parts(rec)
        member = Member(float(tau), float(cfg.tv_xy_weight), float(cfg.tv_z_weight), rec,
                        parts_shared_from=shared_from if shared_from is not None else kept_by, parts_shared=shared)
        if k == 0 and rec.parts_choice is not None and "validation" in rec.parts_choice.chosen_by.values():
            if kept_auto_parts(rec):
                # its tests kept parts and every stage ran again with them: the later members start with them (where
                # the pilot kept them, or the finest stage alone ran again, a member's own path costs no first pass)
                first = rec if rec.parts_choice.rerun == "stages" else None
            else:
                shared_from = float(tau)  # its tests kept nothing: the later members run with the parts off
        member.validation_error, member.image_errors = _held_out_errors(rec)
        member.seconds = before_s + time.perf_counter() - t0
        members.append(member)
        if keep is not None:
            keep(member)
    pick, reason = verdict(members)
    if members[pick].validation_error is None:
        warnings.warn("tv_family: without held-out images (validation_fraction 0, or too few images) the family has no "
                      "verdict; the smallest weight is marked as the pick: look at the members yourself",
                      FDTWarning, stacklevel=2)
    members[pick].picked = True
    return Family(members, pick, reason)


def family_entries(family: Family, reports: dict[float, dict[str, Any]], paths: list[str | None] | None = None) -> list[dict[str, Any]]:
    """RI.json's ``regularisation.family``: each member's :meth:`Member.to_dict`, its ``path`` (``paths[k]``, None where
    it is not written) and, where its report has a truth, its ``relative_delta_n_error``."""
    out = []
    for k, m in enumerate(family.members):
        entry = {**m.to_dict(), "path": None if paths is None else paths[k]}
        metrics = (reports.get(m.tau) or {}).get("metrics") or {}
        if "relative_delta_n_error" in metrics:
            entry["relative_delta_n_error"] = metrics["relative_delta_n_error"]
        out.append(entry)
    return out


def with_family(report: dict[str, Any], entries: list[dict[str, Any]], pick_tau: float, reason: str,
                member_tau: float | None = None, why: str | None = None) -> dict[str, Any]:
    """A member's report with the family's verdict (``regularisation.family``: ``entries``; ``family_pick``: the pick's
    weight and ``reason``) and, for a member kept as the result, ``regularisation.family_member``: which member this
    volume is (``member_tau``) and ``why`` it was kept (default: it is the pick)."""
    reg = {**report.get("regularisation", {}), "family": entries, "family_pick": {"tau": pick_tau, "reason": reason}}
    if member_tau is not None:
        reg["family_member"] = {"tau": member_tau, "picked": member_tau == pick_tau, "why": why or "the pick: " + reason}
    return {**report, "regularisation": reg}
