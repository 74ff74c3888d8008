"""The FDT reconstruction widget: solver settings, a background run streaming the RI volume, and results.

The run is :func:`napari_fdt.napari.jobs.job.reconstruction_job` (the solver loop of ``fdt reconstruct``), in a process of
its own relayed by a napari worker thread (:meth:`~napari_fdt.napari.widgets.widget_tasks.BackgroundTasks.stream`, the widgets'
one way to run background work). The GUI thread only receives updates: the RI layer (absolute RI, physical scale) is
updated in place at every stage end and at most every ``UPDATE_INTERVAL_S`` in between; the progress
bar, time left and loss terms at every snapshot; the sources points layer with the calibrated positions.
*Cancel* takes effect at the next iteration and leaves the last complete stage. Errors appear in the
widget and as napari notifications. Closing the viewer stops the run (it waits for the current
iteration to finish). Settings are saved and loaded in the format of ``fdt reconstruct --config``.
The result actions (save, predicted vs measured, coverage) compute in worker threads too
(:class:`~napari_fdt.napari.widgets.widget_tasks.BackgroundTasks`), their button disabled while they run.
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np
from magicgui.widgets import CheckBox, ComboBox, Container, Label, LineEdit, ProgressBar, PushButton, SpinBox

from napari_fdt.errors import FDTInputError
from napari_fdt.napari.jobs.job import JobResult, Update
from napari_fdt.napari.jobs.remote_job import ComputeProcessDied, RunResult, remote_reconstruction
from napari_fdt.napari.jobs.resume import checkpoint_folder, interrupted_run
from napari_fdt.napari.layers import (
    META_ACQUISITION,
    META_ID,
    META_KIND,
    META_PATH,
    META_REPORT,
    ri_layer,
)
from napari_fdt.napari.result_view import content_slice, keep_view, results_line, ri_contrast_limits, show_bounds, show_slice, truth_error
from napari_fdt.napari.settings import format_stages
from napari_fdt.napari.widgets.plan_line import PLAN_PREFIX, plan_line
from napari_fdt.napari.widgets.schema_widgets import schema_widget
from napari_fdt.napari.widgets.widget_curve import ErrorCurveWidget
from napari_fdt.napari.widgets.widget_layers import acquisition_layer_choices, acquisition_of, follow_layers, refresh_layer_choice, set_sources, sources_for
from napari_fdt.napari.widgets.widget_layout import claim_dock_height, follow_ndisplay, sections_panel, tighten
from napari_fdt.napari.widgets.widget_results import ResultActions, with_tiff_suffix
from napari_fdt.napari.widgets.widget_settings import SETTING_FIELDS, SettingsFileActions
from napari_fdt.napari.widgets.widget_tasks import BackgroundTasks, CloseWatcher, Feedback
from napari_fdt.recon.loop.phases import CANDIDATE_PHASES
from napari_fdt.recon.run.report import describe_parts
from napari_fdt.recon.settings.config import SolverConfig, resolve_stage_lengths

if TYPE_CHECKING:  # pragma: no cover
    import napari

__all__ = ["ReconstructionWidget", "UPDATE_INTERVAL_S", "device_choices", "with_tiff_suffix"]


def _duration(seconds: float) -> str:
    """``42 s``, ``3 min 05 s``, ``1 h 02 min``."""
    s = int(round(max(0.0, seconds)))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {(s % 3600) // 60:02d} min"

#: Least time between two updates of the RI layer within a stage, s (stage ends always update).
UPDATE_INTERVAL_S = 0.5



def device_choices() -> list[str]:
    """``auto`` and the devices present: ``cpu``, and ``cuda`` where torch sees one."""
    import torch

    return ["auto", "cpu"] + (["cuda"] if torch.cuda.is_available() else [])


class ReconstructionWidget(ResultActions, SettingsFileActions, Container):
    """Dock widget: settings, Reconstruct / Cancel, progress, and the results of the last run."""

    def __init__(self, napari_viewer: "napari.viewer.Viewer") -> None:
        super().__init__(labels=False)  # rows below carry their own labels; status and results span the width
        self._viewer = napari_viewer
        self._base = SolverConfig()
        d = self._base
        self.layer = ComboBox(label="acquisition", choices=self._choices)
        self.stages = LineEdit(label="stages", value=format_stages(d.stages),
                               tooltip="factor x iterations per stage, coarse to fine, e.g. 4x100, 2x100, 1x160")
        # Settings generated from the schema: bounds, defaults, choices and tooltips are SolverConfig's.
        f = self._setting
        self.coarse_model = f("coarse_model", "model of coarse stages", "coarse model")
        self.batch_size = f("batch_size", "batch size")
        self.l1_l2_total = f("l1_l2_total", "pixel error weight", "L1 + L2 loss weight", step=0.01)
        self.ssim_weight = f("ssim_weight", "image structure weight", "SSIM loss weight", step=0.01)
        self.tv_xy_weight = f("tv_xy_weight", "smoothing across (xy)", "total variation (TV) weight, xy", step=1e-3)
        self.tv_z_weight = f("tv_z_weight", "smoothing in depth (z)", "total variation (TV) weight, z", step=1e-3)
        self.calibrate_sources = f("calibrate_sources", "calibrate source positions")
        self.calibrate_gain = f("calibrate_gain", "calibrate source brightness", "per-image gain")
        self.calibrate_source_depth = f("calibrate_source_depth", "calibrate source depth")
        self.calibrate_pixel_size = f("calibrate_pixel_size", "calibrate pixel size")
        self.calibrate_slice_spacing = f("calibrate_slice_spacing", "calibrate slice spacing")
        self.calibration_from_stage = SpinBox(
            name="calibration_from_stage", label="calibrate from stage", value=d.calibration_from_stage + 1, min=1,
            max=99, tooltip="first stage (1 = the first, as the status line counts) with position/optics calibration; "
                            "gains are calibrated from the start")
        self.pixel_integration = f("pixel_integration", "pixel integration")
        self.obliquity_correction = f("obliquity_correction", "tilted-ray correction", "obliquity correction")
        self.calibrate_pupil = f("calibrate_pupil", "fit pupil (NA, edge)")
        self.calibrate_aberrations = f("calibrate_aberrations", "fit aberrations")
        self.sub_slices = f("sub_slices", "screens per slice")
        #: which optional parts the last run needed, and why (RI.json's model_parts)
        self.parts_info = Label(value="")
        self.coherence = f("coherence", "coherent-light model", "partial coherence model")
        self.mask_threshold = f("mask_threshold", "coherent-area threshold", "coherence mask threshold", step=0.05)
        self.masks_button = PushButton(text="Preview masks")
        self.device = ComboBox(label="device", choices=device_choices(), value="auto")
        self.seed = f("seed", "seed")
        self.snapshot_every = f("snapshot_every", "progress every (it)")
        self.validation_fraction = f("validation_fraction", "validation share", step=0.05)
        self.early_stopping = f("early_stopping", "early stopping")
        self.half_set_resolution = f("half_set_resolution", "estimate resolution (2 half runs)")
        self.error_bounds = f("error_bounds", "error bound (2 more runs)")
        self.save_settings_button = PushButton(text="Save settings…")
        self.load_settings_button = PushButton(text="Load settings…")
        self.run_button = PushButton(text="Reconstruct")
        self.cancel_button = PushButton(text="Cancel", enabled=False)
        #: shown when the selected acquisition has an interrupted run's checkpoints (napari_fdt.napari.jobs.resume)
        self.resume_run = CheckBox(text="resume the interrupted run", value=False, visible=False)
        self.resume_offer = None
        self.progress = ProgressBar(label="progress", value=0, min=0, max=1)
        self.status = Label(value="")
        #: the last run's key numbers (image fit, validation error, error against a loaded truth), above the fold
        self.results = Label(value="")
        self.losses = Label(value="")
        self.curve = ErrorCurveWidget()
        self.curve_caption = Label(value="")
        self.save_button = PushButton(text="Save RI…", enabled=False)
        self.command_button = PushButton(text="Copy command", enabled=False,
                                         tooltip="the fdt reconstruct line that repeats this run (settings written beside "
                                                 "the acquisition folder), copied to the clipboard")
        self.compare_index = SpinBox(label="image", min=0, max=0)
        self.compare_button = PushButton(text="Predicted vs measured", enabled=False)
        self.coverage_button = PushButton(text="Illumination coverage")
        self.feedback = Feedback()
        self.tasks = BackgroundTasks(napari_viewer, self.feedback, self.native, refresh=lambda: self._set_running(self.running))
        solver = Container(widgets=[self.stages, self.coarse_model, self.batch_size, self.l1_l2_total, self.ssim_weight,
                                    self.tv_xy_weight, self.tv_z_weight])
        calibration = Container(widgets=[self.calibrate_sources, self.calibrate_gain, self.calibrate_source_depth,
                                         self.calibrate_pixel_size, self.calibrate_slice_spacing, self.calibration_from_stage])
        coherence = Container(widgets=[self.coherence, self.mask_threshold, self.masks_button])
        parts = Container(widgets=[self.sub_slices, self.pixel_integration, self.obliquity_correction, self.calibrate_pupil,
                                   self.calibrate_aberrations, self.parts_info])
        run = Container(widgets=[
            self.device, self.seed, self.snapshot_every, self.validation_fraction, self.early_stopping, self.half_set_resolution, self.error_bounds,
            Container(widgets=[self.save_settings_button, self.load_settings_button], layout="horizontal", labels=False)])
        self.details = Container(widgets=[self.losses, self.curve_caption])
        results = Container(widgets=[self.compare_index, self.compare_button, self.coverage_button])
        self.extend([
            Container(widgets=[self.layer, self.progress]),
            Container(widgets=[self.run_button, self.cancel_button], layout="horizontal", labels=False),
            self.resume_run, self.status, self.results,
            Container(widgets=[self.save_button, self.command_button], layout="horizontal", labels=False),
            self.feedback.label,
        ])
        from qtpy.QtWidgets import QSizePolicy

        for w in (self.status, self.results, self.losses, self.curve_caption, self.parts_info):
            w.native.setWordWrap(True)
            # the dock's whole width (a word-wrapped QLabel otherwise keeps its narrow size hint)
            w.native.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Preferred)
        # the error curve sits under its caption (a plain Qt widget in the container's layout)
        self.details.native.layout().addWidget(self.curve)
        self.sections = sections_panel([
            ("Solver", solver, True), ("Self-calibration", calibration, False),
            ("Model parts (auto: chosen by the held-out images)", parts, False), ("Coherence", coherence, False),
            ("Run settings", run, True), ("Run details (losses, error curve)", self.details, True),
            ("Results", results, False)], height_px=420)
        tighten(self, (4, 2, 4, 2))
        self.native.layout().insertWidget(1, self.sections, 1)
        claim_dock_height(self.native)
        self.masks_button.changed.connect(self.preview_masks)
        self.command_button.changed.connect(self.copy_command)
        for name in SETTING_FIELDS:  # an error about a setting goes once the settings are edited; the plan's line follows them
            getattr(self, name).changed.connect(self._clear_stale_error)
            getattr(self, name).changed.connect(self._show_plan)
        self.device.changed.connect(self._clear_stale_error)
        self.device.changed.connect(self._show_plan)
        # run state
        self._worker = None
        self._rec = None
        self._report: dict[str, Any] | None = None
        self._stop = threading.Event()
        self._done = threading.Event()
        self._done.set()
        self._closing = threading.Event()
        self._ri_layer = None
        self._acq_layer = None
        self._close_watcher = None
        self._run_name = ""
        self._runs = 0
        self._n_stages = 0
        #: where along the run's plan (iterations) the last complete stage ended
        self._complete_at = 0
        #: (stages completed, absolute RI) of the last stage end that reached the widget (kept if the process dies)
        self._last_complete: tuple[int, np.ndarray] | None = None
        #: the job the computation process runs, "module:function" (napari_fdt.napari.jobs.remote_job.JOB_TARGET)
        self.job_target: str | None = None
        self.last_command: str | None = None
        self.cancelled = False
        #: (stage, iteration, stage_complete) of every update written into the RI layer (for tests and logs).
        self.layer_updates: list[tuple[int, int, bool]] = []
        self.run_button.changed.connect(self.start)
        self.cancel_button.changed.connect(self.cancel)
        self.save_settings_button.changed.connect(self._save_settings_dialog)
        self.load_settings_button.changed.connect(self._load_settings_dialog)
        self.save_button.changed.connect(self._save_result_dialog)
        self.compare_button.changed.connect(lambda: self.show_comparison(int(self.compare_index.value)))
        self.coverage_button.changed.connect(self.show_coverage)
        self.layer.changed.connect(self._on_layer_changed)
        follow_ndisplay(napari_viewer)
        follow_layers(napari_viewer, self.layer, self._refresh)

    def _setting(self, name: str, label: str, physics: str | None = None, step: float | None = None):
        """The widget of SolverConfig field ``name`` (schema bounds, default, choices, description as tooltip).

        ``label`` is in plain words; the tooltip starts with the physics name (``physics``, else the label) and the
        field's name in settings files and on the command line, then the schema's description."""
        widget = schema_widget(SolverConfig, name, label=label, value=getattr(self._base, name), step=step)
        widget.tooltip = f"{physics or label} ({name}): {widget.tooltip}"
        return widget

    # -- layers -------------------------------------------------------------------------------
    def _choices(self, _widget=None) -> list[tuple[str, object]]:
        return acquisition_layer_choices(self._viewer)

    def _refresh(self, _event=None) -> None:
        refresh_layer_choice(self.layer)
        self._on_layer_changed(self.layer.value)

    def _on_layer_changed(self, layer=None) -> None:
        if layer is not None:
            self.compare_index.max = max(0, int(np.shape(layer.data)[0]) - 1)
            for event in (layer.events.scale, layer.events.translate):  # Apply optics changes them: re-check
                event.connect(self._update_run_state)
        self._update_run_state()
        self._offer_resume()

    def _offer_resume(self) -> None:
        """Show "resume the interrupted run" where the selected acquisition's checkpoint folder holds one."""
        layer = self.layer.value
        offer = None if layer is None or self.running else interrupted_run(checkpoint_folder(layer.metadata.get(META_PATH)))
        self.resume_offer = offer
        self.resume_run.visible = offer is not None
        if offer is None:
            self.resume_run.value = False
        else:
            self.resume_run.text = f"resume the interrupted run ({offer.short()})"  # fits a docked widget's width
            self.resume_run.tooltip = (f"{offer.describe()}; it goes on with its own settings. Its checkpoints: {offer.folder}; "
                                       "unticked, Reconstruct starts afresh and deletes them")

    def _clear_stale_error(self, _value=None) -> None:
        if self.feedback.last_error is not None:
            self.feedback.info("")

    def run_problem(self) -> str | None:
        """Why Reconstruct is disabled (no image stack, or its optics missing, naming the fields), or None."""
        try:
            acquisition_of(self.layer.value)
        except FDTInputError as exc:
            return str(exc)
        return None

    def _update_run_state(self, _event=None) -> None:
        if self.running:
            return
        problem = self.run_problem()
        self.run_button.enabled = problem is None
        self.masks_button.enabled = problem is None and not self.tasks.is_running("masks")
        if problem is not None:
            self.status.value = f"Reconstruct needs: {problem}"
        elif self.status.value.startswith("Reconstruct needs"):
            self.status.value = ""
        self._show_plan()

    def _show_plan(self, _value=None) -> None:
        """Before a run, the status says what Reconstruct would take (:mod:`~napari_fdt.napari.widgets.plan_line`)."""
        if self.running or (self.status.value and not self.status.value.startswith(PLAN_PREFIX)):
            return
        try:
            layer = self.layer.value
            acq = acquisition_of(layer)
            line = plan_line(acq, self.config(), self.device.value, sources_for(self._viewer, layer, acq, required=False))
        except FDTInputError:
            line = ""
        self.status.value = line

    # -- the run ------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        """True while a reconstruction thread is alive."""
        return not self._done.is_set()

    def start(self) -> None:
        """Check everything, then start the reconstruction in a worker thread (a new RI layer for this run)."""
        if self.running:
            return
        worker = None
        with self.feedback.guard():
            layer = self.layer.value
            acq = acquisition_of(layer)
            config = self.config()
            # the stages as the solver will run them (the finest lengthened for large acquisitions): progress and time left
            run_config = resolve_stage_lengths(config, acq.n_images)
            sources = sources_for(self._viewer, layer, acq, required=False)
            device = self.device.value
            folder = checkpoint_folder(layer.metadata.get(META_PATH))
            resume = bool(self.resume_offer is not None and self.resume_run.value)
            self.feedback.info("")
            self._acq_layer = layer
            self._rec, self._report, self.cancelled = None, None, False
            self.layer_updates = []
            self._last_complete = None
            stop, done, closing = threading.Event(), threading.Event(), threading.Event()
            self._runs += 1
            self._run_name = f"{layer.name} RI #{self._runs} ({format_stages(config.stages)}, seed {config.seed})"
            # one layer per run (earlier runs are kept), added when the first volume arrives: a uniform placeholder
            # would cover the images with one flat colour until then
            self._ri_layer = None
            self._close_result()  # the previous run's computation process (its solver, its GPU memory)
            self._n_stages = len(run_config.stages)
            worker = self.tasks.stream(  # the solver runs in a process of its own (napari_fdt.napari.jobs.remote_job: why)
                remote_reconstruction, acq, config, device=device, initial_sources_um=sources, stop=stop,
                done=done, closing=closing, min_interval_s=UPDATE_INTERVAL_S,
                acquisition_path=layer.metadata.get(META_PATH), target=self.job_target,
                checkpoint_dir=None if folder is None else str(folder), resume=resume,
                on_yield=self._on_update, on_result=self._on_returned, on_error=self._on_error,
                on_warning=self._on_warning, on_finished=self._on_finished,
            )
            self._worker = worker
            self._stop, self._done, self._closing = stop, done, closing
            #: where along the run's plan the last complete stage ended (the bar goes back there after a cancel)
            self._complete_at = 0
            self.progress.max = max(1, run_config.total_iterations)  # until the first snapshot brings the plan's count
            self.progress.value = 0
            self.curve.reset(run_config.total_iterations)
            self.curve_caption.value = ""
            self.losses.value = ""
            self._set_running(True)
            self.results.value = ""
            self.status.value = f"run #{self._runs}: {'resuming' if resume else 'starting'} the computation process on {device}…"
            self.resume_run.visible, self.resume_offer = False, None
            if run_config.stages[-1].iterations != config.stages[-1].iterations:
                self.status.value += (f" (finest stage {run_config.stages[-1].iterations} iterations, not {config.stages[-1].iterations}: "
                                      f"{config.final_stage_min_passes:g} passes over the {acq.n_images} images)")
            self._watch_close()
            self._t0 = time.perf_counter()
        if worker is not None:  # started outside the guard's warning capture (see widget_tasks._THREADS)
            worker.start()

    def cancel(self) -> None:
        """Stop at the next iteration; the RI layer then shows the last complete stage."""
        if self.running:
            self._stop.set()
            self.status.value = "cancelling at the next iteration…"

    def _set_running(self, running: bool) -> None:
        self.run_button.enabled = not running and self.run_problem() is None
        self.cancel_button.enabled = running
        self.load_settings_button.enabled = not running
        has_result = (not running) and self._rec is not None and self._report is not None
        self.save_button.enabled = has_result and not self.tasks.is_running("save")
        self.command_button.enabled = not running and self.layer.value is not None
        self.compare_button.enabled = has_result and not self.tasks.is_running("comparison")
        self.coverage_button.enabled = not self.tasks.is_running("coverage")
        self.masks_button.enabled = self.run_problem() is None and not self.tasks.is_running("masks")

    def _watch_close(self) -> None:
        """Stop the run when napari's window closes; a user closing it is asked once, the run named."""
        if self._close_watcher is None:
            self._close_watcher = CloseWatcher(self.native.window(), self._on_viewer_closing, confirm=self._confirm_close)

    def _confirm_close(self) -> bool:
        """Ask before closing napari during a run; True: close (the run stops)."""
        if not self.running:
            return True
        from qtpy.QtWidgets import QMessageBox

        answer = QMessageBox.question(
            self.native.window(), "napari-fdt: reconstruction running",
            f"The reconstruction {self._run_name} is running ({self.status.value}).\n\n"
            "Close napari and stop it? Nothing of this run is saved.",
            QMessageBox.StandardButton.Yes | QMessageBox.StandardButton.No, QMessageBox.StandardButton.No)
        return answer == QMessageBox.StandardButton.Yes

    def _on_viewer_closing(self) -> bool:
        """The viewer closes: end the computation process (a run's is killed at once) and wait until the thread that
        relayed it has ended (at most 10 s)."""
        self._close_result()
        if not self.running:
            return False
        self._closing.set()
        self._stop.set()
        self._done.wait(timeout=10.0)
        return True

    def _on_update(self, update: Update) -> None:
        if self._closing.is_set():
            return
        if update.kind == "started":
            return
        if update.kind in ("evaluating", "resolution", "bounds"):
            self.status.value = {"evaluating": "evaluating the fit of every image…",
                                 "resolution": "estimating the resolution: each half of the images reconstructed again (Cancel keeps the result)…",
                                 "bounds": "error bound: the result re-simulated and reconstructed again (Cancel keeps the result)…"}[update.kind]
            return
        snap = update.snapshot
        # one bar for the whole plan (the stages, the TV trials, the stages run again with kept parts): it never restarts
        self.progress.max = max(1, int(snap.plan_iterations))
        self.progress.value = min(int(snap.plan_iteration), self.progress.max)
        left_txt = f", about {_duration(snap.eta_s)} left" if snap.eta_s and snap.eta_s > 0 else ""
        most = getattr(snap, "eta_up_to_s", None)
        if left_txt and most is not None:  # choices still open
            left_txt += f" (up to {_duration(most)}, as the data choose)"
        tried = f", tried xy {snap.tv_weights[0]:g}, z {snap.tv_weights[1]:g}" if snap.tv_weights is not None else ""
        where = "" if snap.phase in CANDIDATE_PHASES else f", iteration {snap.iteration}/{snap.stage_iterations}"
        self.status.value = (f"run #{self._runs}: {snap.phase_name}{tried}{where}; "
                             f"{_duration(snap.elapsed_s)} elapsed{left_txt}")
        self.losses.value = "loss: " + ", ".join(f"{k} {v:.4g}" for k, v in snap.losses.items())
        if snap.phase in CANDIDATE_PHASES:  # a TV trial's volume is a candidate, the pupil pilot's zero: no curve point
            return
        if snap.stage_complete:
            self._complete_at = int(snap.plan_iteration)
        self.curve.add(snap)
        self.curve_caption.value = "error: " + self.curve.curve.caption()
        if update.ri is not None:
            self._show_ri(update.ri)
            self.layer_updates.append((snap.stage, snap.iteration, snap.stage_complete))
            if snap.stage_complete:
                self._last_complete = (snap.stage + 1, update.ri)
            # (no warning capture here: the worker owns the process's warning hook while it runs)
            self._put_sources(snap.sources_um)

    def _calibrated_name(self) -> str:
        return f"{self._acq_layer.name} sources calibrated #{self._runs}"

    def _put_sources(self, sources_um: np.ndarray) -> None:
        """The calibrated sources in their layer, without taking the selection or moving the z slider (they lie
        below the volume: a new layer there would widen the z range and pull the slider out of the volume)."""
        with keep_view(self._viewer):
            set_sources(self._viewer, self._acq_layer, sources_um, kind="calibrated", name=self._calibrated_name())

    def _show_ri(self, ri: np.ndarray, *, focus: bool = False) -> None:
        """Write ``ri`` into this run's RI layer (added with the first volume, or again if the user deleted it), with
        contrast limits from the data. A new layer, or ``focus``, selects it and moves the z slider to its slice with
        the most structure; otherwise the view stays where the user has it."""
        layer = self._ri_layer
        n_b = float(self._acq_layer.metadata[META_ACQUISITION].optics.n_background)
        limits = ri_contrast_limits(ri, n_b)
        if layer is None or layer not in self._viewer.layers:
            acq = acquisition_of(self._acq_layer)
            data, kwargs, _ = ri_layer(ri, acq.optics, self._run_name, owner=self._acq_layer.metadata.get(META_ID))
            kwargs["metadata"]["fdt_run"] = self._runs
            kwargs["contrast_limits"] = limits
            self._ri_layer = layer = self._viewer.add_image(data, **kwargs)
            focus = True
        else:
            layer.data = ri
            layer.contrast_limits = limits
        if focus:
            self._viewer.layers.selection.active = layer
            show_slice(self._viewer, layer, content_slice(ri, n_b))

    def _close_result(self) -> None:
        """End the computation process kept for the last run's *Predicted vs measured*."""
        if isinstance(self._rec, RunResult):
            self._rec.close()

    def _on_returned(self, result: JobResult) -> None:
        if self._closing.is_set():
            if isinstance(result.rec, RunResult):
                result.rec.close()
            return
        self._rec = result.rec
        self.cancelled = result.cancelled
        self.feedback.info("")
        if result.ri is None:
            if self._ri_layer is not None and self._ri_layer in self._viewer.layers:
                self._viewer.layers.remove(self._ri_layer)
            for layer in list(self._viewer.layers):
                if layer.name == self._calibrated_name() and layer.metadata.get(META_KIND) == "calibrated":
                    self._viewer.layers.remove(layer)
            self._ri_layer = None
            self._rec = None
            self.progress.value = 0
            self.status.value = f"run #{self._runs} cancelled before the first stage ended: nothing kept"
            return
        self._report = result.report
        parts = (result.report or {}).get("model_parts")
        self.parts_info.value = describe_parts(parts) if parts else ""
        self._show_ri(result.ri, focus=True)
        self._ri_layer.metadata[META_REPORT] = result.report
        self._put_sources(result.sources_um)
        n = len(result.rec.config.stages)
        n_b = float(result.rec.acquisition.optics.n_background)
        if result.extra.get("error_bounds") is not None:
            show_bounds(self._viewer, result.extra["error_bounds"], result.ri, self._ri_layer, n_b)
        self.results.value = results_line(result.report, truth_error(self._viewer, self._acq_layer, result.ri, n_b))
        if result.cancelled:
            self.progress.value = self._complete_at
            self.status.value = (f"run #{self._runs} cancelled: showing the last complete stage "
                                 f"({result.completed_stages}/{n})")
        else:
            self.progress.value = self.progress.max
            self.status.value = f"run #{self._runs} done: {n} stages in {result.rec.elapsed_s:.1f} s on {result.rec.device}"

    def _on_error(self, exc: Exception) -> None:
        if self._closing.is_set():
            return
        if isinstance(exc, ComputeProcessDied) and self._last_complete is not None:
            done, ri = self._last_complete
            self._show_ri(ri, focus=True)
            self.progress.value = self._complete_at
            self.status.value = (f"run #{self._runs} failed: the computation process ended; showing the last complete "
                                 f"stage ({done}/{self._n_stages})")
        else:
            if isinstance(exc, ComputeProcessDied) and self._ri_layer is not None and self._ri_layer in self._viewer.layers:
                self._viewer.layers.remove(self._ri_layer)  # a part of a first stage: nothing complete to keep
                self._ri_layer = None
            self.progress.value = 0
            self.status.value = f"run #{self._runs} failed"
        self.feedback.exception(exc)

    def _on_warning(self, args: tuple) -> None:
        """A warning raised while the worker runs: the core's (FDTWarning) are shown, others go to the log.

        The worker catches every warning shown in the process while it runs (``warnings.showwarning`` is
        global), including ones from the GUI thread.
        """
        if not self._closing.is_set():
            self.feedback.show_warning(args)

    def _on_finished(self) -> None:
        self._worker = None
        if self._closing.is_set():
            return
        self._set_running(False)
        self._offer_resume()
