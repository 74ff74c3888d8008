"""The FDT smoothing-family widget: the volumes at several TV weights, one slider, and the data's verdict beside it.

*Reconstruct the family* runs :func:`napari_fdt.napari.jobs.family_job.family_job` (one whole run per weight,
:mod:`napari_fdt.recon.run.family`) in the computation process. Each member appears as it completes; one RI layer shows
the member the **smoothing** slider points at (sharper to the left, smoother to the right; the weight and the
held-out verdict under it), and at the end the slider goes to the pick and a second layer, *depends on smoothing*,
shows each voxel's range across the members in RI units: what the choice of weight decides. *Save the member shown…*
writes that member with its report, which records which member it is and why it was kept (the user's choice, or the
pick). No physics here.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from magicgui.widgets import ComboBox, Container, Label, ProgressBar, PushButton, Slider

from napari_fdt.napari.jobs.job import JobResult, Update
from napari_fdt.napari.jobs.remote_job import remote_reconstruction
from napari_fdt.napari.layers import META_PATH, ri_layer
from napari_fdt.napari.widgets.widget_layers import acquisition_layer_choices, acquisition_of, follow_layers, refresh_layer_choice, sources_for
from napari_fdt.napari.widgets.widget_reconstruction import device_choices
from napari_fdt.napari.widgets.widget_results import with_tiff_suffix
from napari_fdt.napari.widgets.widget_tasks import BackgroundTasks, CloseWatcher, Feedback
from napari_fdt.recon.settings.config import SolverConfig

if TYPE_CHECKING:  # pragma: no cover
    import napari

__all__ = ["FamilyWidget", "JOB_TARGET", "member_words"]

JOB_TARGET = "napari_fdt.napari.jobs.family_job:family_job"


def member_words(index: int, n: int) -> str:
    """The member's place in words: sharpest, smoothest or between."""
    return "sharpest" if index == 0 else ("smoothest" if index == n - 1 else "between")


class FamilyWidget(Container):
    """Dock widget: acquisition, device, Reconstruct the family / Cancel, the smoothing slider and Save."""

    def __init__(self, napari_viewer: "napari.viewer.Viewer") -> None:
        super().__init__(labels=False)
        self._viewer = napari_viewer
        self.layer = ComboBox(label="acquisition", choices=lambda _w=None: acquisition_layer_choices(self._viewer))
        self.device = ComboBox(label="device", choices=device_choices(), value="auto")
        self.run_button = PushButton(text="Reconstruct the family (3 runs)")
        self.cancel_button = PushButton(text="Cancel", enabled=False)
        self.progress = ProgressBar(label="progress", value=0, min=0, max=1)
        self.status = Label(value="")
        self.smoothing = Slider(label="smoothing", min=0, max=0, value=0, enabled=False,
                                tooltip="sharper (left) to smoother (right): the member shown, by its TV weight")
        self.shown = Label(value="")
        self.verdict = Label(value="")
        self.save_button = PushButton(text="Save the member shown…", enabled=False)
        self.feedback = Feedback()
        self.tasks = BackgroundTasks(napari_viewer, self.feedback, self.native, refresh=lambda: self._set_running(self.running))
        self.extend([Container(widgets=[self.layer, self.device, self.progress]),
                     Container(widgets=[self.run_button, self.cancel_button], layout="horizontal", labels=False),
                     self.status, Container(widgets=[self.smoothing]), self.shown, self.verdict, self.save_button,
                     self.feedback.label])
        for w in (self.status, self.shown, self.verdict):
            w.native.setWordWrap(True)
        #: settings of the members' runs (None: the defaults; tests and scripts give short ones)
        self.config: SolverConfig | None = None
        self.members: list[dict[str, Any]] = []  # index, tau, validation_error, report, ri (in the order of the weights)
        self.family: dict[str, Any] | None = None  # the verdict: entries, pick, reason
        self._ri_layer = self._range_layer = None
        self._acq = None
        self._member: dict[str, Any] | None = None  # the member being computed (index, tau, n_members)
        self._stop, self._done, self._closing = threading.Event(), threading.Event(), threading.Event()
        self._done.set()
        self._close_watcher = None
        self.run_button.changed.connect(self.start)
        self.cancel_button.changed.connect(self.cancel)
        self.smoothing.changed.connect(self._show_member)
        self.save_button.changed.connect(self._save_dialog)
        follow_layers(napari_viewer, self.layer, lambda _e=None: refresh_layer_choice(self.layer))

    # -- the run ------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return not self._done.is_set()

    def start(self) -> None:
        """Start the family in the computation process (each member a whole run)."""
        if self.running:
            return
        worker = None
        with self.feedback.guard():
            layer = self.layer.value
            acq = acquisition_of(layer)
            sources = sources_for(self._viewer, layer, acq, required=False)
            config = self.config or SolverConfig()
            self._acq, self._acq_layer = acq, layer
            self.members, self.family, self._member = [], None, None
            self._ri_layer = self._range_layer = None
            self._stop, self._done, self._closing = threading.Event(), threading.Event(), threading.Event()
            worker = self.tasks.stream(
                remote_reconstruction, acq, config, device=self.device.value, initial_sources_um=sources, stop=self._stop,
                done=self._done, closing=self._closing, acquisition_path=layer.metadata.get(META_PATH), target=JOB_TARGET,
                on_yield=self._on_update, on_result=self._on_returned, on_error=self._on_error,
                on_warning=self._on_warning, on_finished=lambda: self._set_running(False))
            self.smoothing.enabled, self.smoothing.max, self.smoothing.value = False, 0, 0
            self.shown.value = self.verdict.value = ""
            self.status.value = f"starting the computation process on {self.device.value}…"
            self._set_running(True)
            if self._close_watcher is None:
                self._close_watcher = CloseWatcher(self.native.window(), self._on_viewer_closing)
        if worker is not None:
            worker.start()

    def cancel(self) -> None:
        """Stop at the next iteration; the members completed stay."""
        if self.running:
            self._stop.set()
            self.status.value = "cancelling at the next iteration…"

    def _set_running(self, running: bool) -> None:
        self.run_button.enabled = not running
        self.cancel_button.enabled = running
        self.save_button.enabled = bool(self.members) and not self.tasks.is_running("save")

    def _on_viewer_closing(self) -> bool:
        if not self.running:
            return False
        self._closing.set()
        self._stop.set()
        self._done.wait(timeout=10.0)
        return True

    def _on_update(self, update: Update) -> None:
        if self._closing.is_set():
            return
        if update.kind == "member_started":
            info = update.snapshot
            self._member = info
            self.status.value = f"member {info['index'] + 1}/{info['n_members']}: τ_xy {info['tau']:g}…"
        elif update.kind == "snapshot":
            snap = update.snapshot
            self.progress.max = max(1, snap.plan_iterations)
            self.progress.value = min(snap.plan_iteration, self.progress.max)
            info = self._member
            if info is not None:
                self.status.value = (f"member {info['index'] + 1}/{info['n_members']}: τ_xy {info['tau']:g}, "
                                     f"{snap.phase_name} ({snap.phase_iteration}/{snap.phase_iterations} it)")
        elif update.kind == "member":
            self.members.append({**update.snapshot, "ri": np.asarray(update.ri, dtype=np.float32)})
            self.smoothing.max = len(self.members) - 1
            self.smoothing.enabled = len(self.members) > 1
            if self.smoothing.value == len(self.members) - 1:
                self._show_member()
            else:
                self.smoothing.value = len(self.members) - 1  # the newest member, as it arrives
            self._set_running(self.running)

    def _on_returned(self, result: JobResult) -> None:
        if self._closing.is_set():
            return
        extra = result.extra or {}
        if "family" not in extra:
            self.status.value = f"cancelled: {len(self.members)} member(s) complete, no pick"
            return
        self.family = {"entries": extra["family"], "pick": int(extra["pick"]), "reason": extra["reason"]}
        stack = np.stack([m["ri"] for m in self.members])
        data, kwargs, _ = ri_layer(stack.max(axis=0) - stack.min(axis=0), self._acq.optics,
                                   f"{self._acq_layer.name} depends on smoothing (RI range across the members)")
        kwargs.update(colormap="viridis", metadata={})
        self._range_layer = self._viewer.add_image(data, **kwargs)
        self.smoothing.value = self.family["pick"]  # the pick shown first once it is known
        self._show_member()
        lines = []
        for e in self.family["entries"]:
            tell = "≈ the best" if e["indistinguishable_from_best"] else "worse"
            lines.append(f"τ_xy {e['tau']:g}{' (pick)' if e['picked'] else ''}: held-out {e['validation_error']:.4f} ({tell})")
        self.verdict.value = "; ".join(lines) + f". Pick: {self.family['reason']}."
        self.status.value = f"done: {len(self.members)} members; the pick is τ_xy {self.members[self.family['pick']]['tau']:g}"

    def _on_warning(self, args: tuple) -> None:
        """The core's warnings (FDTWarning) are shown; others go to the log."""
        if not self._closing.is_set():
            self.feedback.show_warning(args)

    def _on_error(self, exc: Exception) -> None:
        if not self._closing.is_set():
            self.status.value = "the family failed" + (f" after {len(self.members)} member(s)" if self.members else "")
            self.feedback.exception(exc)

    # -- the member shown ---------------------------------------------------------------------
    def shown_index(self) -> int:
        """The member the slider points at."""
        return int(min(max(0, self.smoothing.value), len(self.members) - 1))

    def _show_member(self, _value=None) -> None:
        if not self.members:
            return
        k = self.shown_index()
        m = self.members[k]
        n = len(self.members) if self.family is None else len(self.family["entries"])
        name = f"{self._acq_layer.name} RI, smoothing family (member shown)"
        if self._ri_layer is None or self._ri_layer not in self._viewer.layers:
            data, kwargs, _ = ri_layer(m["ri"], self._acq.optics, name, report=m["report"])
            self._ri_layer = self._viewer.add_image(data, **kwargs)
        else:
            self._ri_layer.data = m["ri"]
            self._ri_layer.metadata["fdt_report"] = m["report"]
        words = member_words(k, n)
        verdict = ""
        if self.family is not None:
            e = self.family["entries"][k]
            verdict = (" — the pick" if e["picked"] else
                       (" — the images cannot tell it from the best" if e["indistinguishable_from_best"] else " — worse on the held-out images"))
        self.shown.value = f"shown: τ_xy {m['tau']:g} ({words}), held-out error {m['validation_error']:.4f}{verdict}"
        self.smoothing.tooltip = f"τ_xy {m['tau']:g}, τ_z {m['tau'] / 2:g}: sharper (left) to smoother (right)"

    def member_report(self, index: int) -> dict[str, Any]:
        """Member ``index``'s report with the family's verdict and why this member was kept."""
        from napari_fdt.recon.run.family import with_family

        m = self.members[index]
        if self.family is None:  # a member of a cancelled family: no verdict
            reg = {**m["report"].get("regularisation", {}), "family_member": {
                "tau": m["tau"], "picked": False, "why": "a member of an unfinished family, chosen by the user"}}
            return {**m["report"], "regularisation": reg}
        pick = self.members[self.family["pick"]]["tau"]
        why = None if m["tau"] == pick else f"chosen by the user in napari (the pick was τ_xy {pick:g})"
        return with_family(m["report"], self.family["entries"], pick, self.family["reason"], member_tau=m["tau"], why=why)

    def save_shown(self, path: str | Path) -> tuple[Path, Path]:
        """Write the member shown (OME-TIFF, absolute RI) and its report beside it."""
        from napari_fdt.data.io import report_path, write_json_atomic
        from napari_fdt.data.volumes import write_volume

        path = with_tiff_suffix(path)
        k = self.shown_index()
        o = self._acq.optics
        report = {**self.member_report(k), "output": str(path)}
        write_volume(path, self.members[k]["ri"], (o.slice_spacing_um, o.pixel_size_um, o.pixel_size_um), overwrite=True)
        write_json_atomic(report_path(path), report, overwrite=True)
        return path, report_path(path)

    def _save_dialog(self) -> None:
        from qtpy.QtWidgets import QFileDialog

        if not self.members:
            return
        suggestion = f"RI_tv{self.members[self.shown_index()]['tau']:g}.ome.tif"
        path, _ = QFileDialog.getSaveFileName(self.native, "Save the member shown", suggestion, "OME-TIFF (*.ome.tif *.tif)")
        if path:
            self.tasks.start("save", lambda: self.save_shown(path), lambda w: self.feedback.info(f"wrote {w[0]} and {w[1]}"),
                             buttons=(self.save_button,), message=f"writing {path}…")
