"""The smoothing family as the napari widget runs it (in the computation process, :mod:`napari_fdt.napari.jobs.remote_job`).

:func:`family_job` drives :func:`napari_fdt.recon.run.family.run_family` and yields :class:`~napari_fdt.napari.jobs.job.Update` s:
``"member_started"`` (``snapshot`` a dict: ``index``, ``tau``, ``n_members``), each member's ``"snapshot"`` s (no volume:
members appear whole), and ``"member"`` as each member completes (``ri`` its absolute RI, ``snapshot`` a dict with its
``index``, ``tau``, ``validation_error`` and ``report``). The result's ``report`` is the pick's, with the family's
verdict; ``extra`` holds ``family`` (RI.json's ``regularisation.family``), ``pick``, ``reason`` and every member's
``reports``. Stopped, the members completed stay the widget's; nothing is picked. No Qt here.
"""

from __future__ import annotations

import threading
from typing import Any, Iterator

import numpy as np

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.napari.jobs.job import JobResult, Update
from napari_fdt.recon.run.family import FAMILY_TAUS, family_entries, run_family, with_family
from napari_fdt.recon.settings.config import SolverConfig

__all__ = ["family_job"]


def family_job(acquisition: Acquisition, config: SolverConfig, *, device: str = "auto",
               initial_sources_um: np.ndarray | None = None, stop: threading.Event, done: threading.Event | None = None,
               closing: threading.Event | None = None, acquisition_path: str | None = None, **_ignored: Any) -> Iterator[Update]:
    """Generator: yields :class:`Update` s, returns a :class:`JobResult` (see the module)."""
    from napari_fdt.recon.run.session import finish_run

    try:
        finished: list[dict[str, Any]] = []

        def keep(member) -> None:  # (inside run_family, before the next member's first snapshot)
            report = finish_run(member.rec, False, acquisition_path=acquisition_path)
            finished.append({"index": len(finished), "tau": member.tau, "validation_error": member.validation_error,
                             "report": report, "ri": member.rec.ri_full()})

        sent, current = 0, -1
        runs = run_family(acquisition, config, device=device,
                          initial_sources_um=initial_sources_um, should_stop=stop.is_set, keep=keep)
        family = None
        while True:
            try:
                k, snap = next(runs)
            except StopIteration as end:
                family = end.value
                break
            while sent < len(finished):  # a member completed before this snapshot
                yield _member_update(finished[sent])
                sent += 1
            if k != current:
                current = k
                yield Update("member_started", snapshot={"index": k, "tau": FAMILY_TAUS[k], "n_members": len(FAMILY_TAUS)})
            yield Update("snapshot", snapshot=snap)
        while sent < len(finished):
            yield _member_update(finished[sent])
            sent += 1
        if family is None or (closing is not None and closing.is_set()):
            return JobResult(None, True, 0, extra={"members": len(finished)})
        reports = {m["tau"]: m["report"] for m in finished}
        entries = family_entries(family, reports)
        chosen = family.chosen
        report = with_family(reports[chosen.tau], entries, chosen.tau, family.reason, member_tau=chosen.tau)
        return JobResult(chosen.rec, False, chosen.rec.completed_stages, ri=finished[family.pick]["ri"],
                         sources_um=chosen.rec.sources_um(), report=report,
                         extra={"family": entries, "pick": family.pick, "reason": family.reason,
                                "reports": [m["report"] for m in finished]})
    finally:
        if done is not None:
            done.set()


def _member_update(member: dict[str, Any]) -> Update:
    info = {k: member[k] for k in ("index", "tau", "validation_error", "report")}
    return Update("member", snapshot=info, ri=member["ri"])
