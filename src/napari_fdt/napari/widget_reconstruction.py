"""The FDT reconstruction widget: solver settings, a background run streaming the RI volume, and results.

The run is :func:`napari_fdt.napari.job.reconstruction_job` (the solver loop of ``fdt reconstruct``) in a napari
``thread_worker``. The GUI thread only receives updates: the RI layer (absolute RI, physical scale) is
updated in place at every stage end and at most every ``UPDATE_INTERVAL_S`` in between; the progress
bar, time left and loss terms at every snapshot; the sources points layer with the calibrated positions.
*Cancel* takes effect at the next iteration and leaves the last complete stage. Errors appear in the
widget and as napari notifications. Closing the viewer stops the run (it waits for the current
iteration to finish). Settings are saved and loaded in the format of ``fdt reconstruct --config``.
The result actions (save, predicted vs measured, coverage) compute in worker threads too
(:class:`~napari_fdt.napari.widget_common.BackgroundTasks`), their button disabled while they run.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from magicgui.widgets import ComboBox, Container, Label, LineEdit, ProgressBar, PushButton, SpinBox

from napari_fdt.errors import FDTInputError
from napari_fdt.napari.compute import check_index, illumination_coverage, mask_stack, predicted_vs_measured
from napari_fdt.napari.job import JobResult, TimeLeft, Update, reconstruction_job, stage_costs
from napari_fdt.napari.layers import (
    META_ACQUISITION,
    META_ID,
    META_KIND,
    META_OWNER,
    META_PATH,
    META_REPORT,
    STACK_AXIS_LABELS,
    STACK_UNITS,
    UNITS,
    lateral_translate,
    ri_layer,
    side_by_side,
    stack_scale,
    stack_translate,
    volume_scale,
    volume_translate,
)
from napari_fdt.napari.schema_widgets import schema_widget
from napari_fdt.napari.settings import format_stages, merge_config, unique_path
from napari_fdt.napari.widget_common import (
    BackgroundTasks,
    CloseWatcher,
    Feedback,
    acquisition_layer_choices,
    acquisition_of,
    claim_dock_height,
    follow_layers,
    follow_ndisplay,
    put_layer,
    refresh_layer_choice,
    sections_panel,
    set_sources,
    sources_for,
    tighten,
    track_thread,
)
from napari_fdt.napari.widget_curve import ErrorCurveWidget
from napari_fdt.recon.command import format_command, reconstruct_command
from napari_fdt.recon.config import SolverConfig, load_config, resolve_stage_lengths
from napari_fdt.recon.report import describe_parts

if TYPE_CHECKING:  # pragma: no cover
    import napari

__all__ = ["ReconstructionWidget", "UPDATE_INTERVAL_S", "device_choices", "with_tiff_suffix"]


def with_tiff_suffix(path: str | Path) -> Path:
    """``path`` with ``.ome.tif`` added when it has no ``.tif``/``.tiff`` suffix (``my_cells_RI`` → ``my_cells_RI.ome.tif``)."""
    path = Path(path)
    return path if path.suffix.lower() in (".tif", ".tiff") else path.with_name(path.name + ".ome.tif")


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

#: Settings the widget edits, by widget attribute (= SolverConfig field).
_FIELDS = ("stages", "coarse_model", "batch_size", "l1_l2_total", "ssim_weight", "tv_xy_weight", "tv_z_weight",
           "calibrate_sources", "calibrate_gain", "calibrate_source_depth", "calibrate_pixel_size",
           "calibrate_slice_spacing", "calibration_from_stage", "coherence", "mask_threshold", "seed", "snapshot_every",
           "validation_fraction", "early_stopping", "pixel_integration", "obliquity_correction", "calibrate_pupil",
           "calibrate_aberrations", "parts_rerun", "parts_test_images")
#: Settings the widget numbers from 1 (as the status line does) while the configuration counts from 0.
_ONE_BASED = ("calibration_from_stage",)


def device_choices() -> list[str]:
    """``auto`` and the devices present: ``cpu``, and ``cuda`` where torch sees one."""
    import torch

    return ["auto", "cpu"] + (["cuda"] if torch.cuda.is_available() else [])


class ReconstructionWidget(Container):
    """Dock widget: settings, Reconstruct / Cancel, progress, and the results of the last run."""

    def __init__(self, napari_viewer: "napari.viewer.Viewer") -> None:
        super().__init__(labels=True)
        self._viewer = napari_viewer
        self._base = SolverConfig()
        d = self._base
        self.layer = ComboBox(label="acquisition", choices=self._choices)
        self.stages = LineEdit(label="stages", value=format_stages(d.stages),
                               tooltip="factor x iterations per stage, coarse to fine, e.g. 4x100, 2x100, 1x160")
        # Settings generated from the schema: bounds, defaults, choices and tooltips are SolverConfig's.
        f = self._setting
        self.coarse_model = f("coarse_model", "coarse model")
        self.batch_size = f("batch_size", "batch size")
        self.l1_l2_total = f("l1_l2_total", "L1 + L2 weight", step=0.01)
        self.ssim_weight = f("ssim_weight", "SSIM weight", step=0.01)
        self.tv_xy_weight = f("tv_xy_weight", "TV xy weight", step=1e-3)
        self.tv_z_weight = f("tv_z_weight", "TV z weight", step=1e-3)
        self.calibrate_sources = f("calibrate_sources", "calibrate source positions")
        self.calibrate_gain = f("calibrate_gain", "calibrate gains")
        self.calibrate_source_depth = f("calibrate_source_depth", "calibrate source depth")
        self.calibrate_pixel_size = f("calibrate_pixel_size", "calibrate pixel size")
        self.calibrate_slice_spacing = f("calibrate_slice_spacing", "calibrate slice spacing")
        self.calibration_from_stage = SpinBox(
            name="calibration_from_stage", label="calibrate from stage", value=d.calibration_from_stage + 1, min=1,
            max=99, tooltip="first stage (1 = the first, as the status line counts) with position/optics calibration; "
                            "gains are calibrated from the start")
        self.pixel_integration = f("pixel_integration", "pixel integration")
        self.obliquity_correction = f("obliquity_correction", "obliquity correction")
        self.calibrate_pupil = f("calibrate_pupil", "fit pupil (NA, edge)")
        self.calibrate_aberrations = f("calibrate_aberrations", "fit aberrations")
        self.parts_rerun = f("parts_rerun", "rerun with kept parts")
        self.parts_test_images = f("parts_test_images", "parts tested on")
        #: which optional parts the last run needed, and why (RI.json's model_parts)
        self.parts_info = Label(value="")
        self.coherence = f("coherence", "coherence")
        self.mask_threshold = f("mask_threshold", "mask threshold", step=0.05)
        self.masks_button = PushButton(text="Preview masks")
        self.device = ComboBox(label="device", choices=device_choices(), value="auto")
        self.seed = f("seed", "seed")
        self.snapshot_every = f("snapshot_every", "progress every (it)")
        self.validation_fraction = f("validation_fraction", "validation share", step=0.05)
        self.early_stopping = f("early_stopping", "early stopping")
        self.save_settings_button = PushButton(text="Save settings…")
        self.load_settings_button = PushButton(text="Load settings…")
        self.run_button = PushButton(text="Reconstruct")
        self.cancel_button = PushButton(text="Cancel", enabled=False)
        self.progress = ProgressBar(label="progress", value=0, min=0, max=1)
        self.status = Label(value="")
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
        parts = Container(widgets=[self.pixel_integration, self.obliquity_correction, self.calibrate_pupil,
                                   self.calibrate_aberrations, self.parts_rerun, self.parts_test_images, self.parts_info])
        run = Container(widgets=[
            self.device, self.seed, self.snapshot_every, self.validation_fraction, self.early_stopping,
            Container(widgets=[self.save_settings_button, self.load_settings_button], layout="horizontal", labels=False)])
        self.details = Container(widgets=[self.losses, self.curve_caption])
        results = Container(widgets=[self.compare_index, self.compare_button, self.coverage_button])
        self.extend([
            Container(widgets=[self.layer]),
            Container(widgets=[self.run_button, self.cancel_button], layout="horizontal", labels=False),
            self.progress, self.status,
            Container(widgets=[self.save_button, self.command_button], layout="horizontal", labels=False),
            self.feedback.label,
        ])
        for w in (self.status, self.losses, self.curve_caption, self.parts_info):
            w.native.setWordWrap(True)
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
        for name in _FIELDS:  # an error about a setting goes once the settings are edited
            getattr(self, name).changed.connect(self._clear_stale_error)
        self.device.changed.connect(self._clear_stale_error)
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
        self._time_left: TimeLeft | None = None
        self._run_name = ""
        self._runs = 0
        self._stage_iterations: list[int] = []
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

    def _setting(self, name: str, label: str, step: float | None = None):
        """The widget of SolverConfig field ``name`` (schema bounds, default, choices, description as tooltip)."""
        return schema_widget(SolverConfig, name, label=label, value=getattr(self._base, name), step=step)

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

    # -- settings -----------------------------------------------------------------------------
    def config(self) -> SolverConfig:
        """The settings in the widget over the last loaded ones, checked (raises :class:`FDTInputError`)."""
        values = {name: getattr(self, name).value for name in _FIELDS}
        for name in _ONE_BASED:
            values[name] = int(values[name]) - 1
        return merge_config(self._base, values)

    def set_config(self, config: SolverConfig) -> None:
        """Show ``config`` in the widget; settings it does not show are kept for saving and running."""
        self._base = config
        for name in _FIELDS:
            value = getattr(config, name)
            getattr(self, name).value = (format_stages(value) if name == "stages" else
                                         value + 1 if name in _ONE_BASED else value)

    def save_settings(self, path: str | Path) -> Path:
        """Write the settings as ``fdt reconstruct --config`` reads them."""
        self.config().save(path)
        return Path(path)

    def load_settings(self, path: str | Path) -> SolverConfig:
        """Read a settings file (JSON, or TOML for ``.toml``) into the widget."""
        config = load_config(path)
        self.set_config(config)
        return config

    def _save_settings_dialog(self) -> None:
        from qtpy.QtWidgets import QFileDialog

        path, _ = QFileDialog.getSaveFileName(self.native, "Save reconstruction settings", "fdt_settings.json", "JSON (*.json)")
        if path:
            with self.feedback.guard():
                self.feedback.info(f"settings written to {self.save_settings(path)}")

    def _load_settings_dialog(self) -> None:
        from qtpy.QtWidgets import QFileDialog

        path, _ = QFileDialog.getOpenFileName(self.native, "Load reconstruction settings", "", "Settings (*.json *.toml)")
        if path:
            with self.feedback.guard():
                self.load_settings(path)
                self.feedback.info(f"settings read from {path}")

    # -- the run ------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        """True while a reconstruction thread is alive."""
        return not self._done.is_set()

    def start(self) -> None:
        """Check everything, then start the reconstruction in a worker thread (a new RI layer for this run)."""
        from superqt.utils import GeneratorWorker  # public superqt API: errors and warnings are shown below

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
            from napari_fdt.device import resolve_device

            device_type = resolve_device(device).type
            self.feedback.info("")
            self._acq_layer = layer
            self._rec, self._report, self.cancelled = None, None, False
            self.layer_updates = []
            stop, done, closing = threading.Event(), threading.Event(), threading.Event()
            self._runs += 1
            self._run_name = f"{layer.name} RI #{self._runs} ({format_stages(config.stages)}, seed {config.seed})"
            n_b = acq.optics.n_background
            data, kwargs, _ = ri_layer(np.full((acq.optics.n_slices, *acq.image_shape), n_b, np.float32),
                                       acq.optics, self._run_name, owner=layer.metadata.get(META_ID))
            kwargs["contrast_limits"] = (n_b, n_b + 0.5 * config.delta_n_max)
            kwargs["metadata"]["fdt_run"] = self._runs
            self._ri_layer = self._viewer.add_image(data, **kwargs)  # one layer per run: earlier runs are kept
            self._stage_iterations = [s.iterations for s in run_config.stages]
            self._time_left = TimeLeft(self._stage_iterations, stage_costs(acq.optics, acq.image_shape, run_config, acq.n_images,
                                                                                device_type))
            worker = GeneratorWorker(
                reconstruction_job, acq, config, device=device, initial_sources_um=sources, stop=stop,
                done=done, closing=closing, min_interval_s=UPDATE_INTERVAL_S,
                acquisition_path=layer.metadata.get(META_PATH),
            )
            worker.yielded.connect(self._on_update)
            worker.returned.connect(self._on_returned)
            worker.errored.connect(self._on_error)
            worker.warned.connect(self._on_warning)
            worker.finished.connect(self._on_finished)
            self._worker = worker
            self._stop, self._done, self._closing = stop, done, closing
            self.progress.max = max(1, run_config.total_iterations)
            self.progress.value = 0
            self.curve.reset(run_config.total_iterations)
            self.curve_caption.value = ""
            self.losses.value = ""
            self._set_running(True)
            self.status.value = f"run #{self._runs}: starting on {device}…"
            if run_config.stages[-1].iterations != config.stages[-1].iterations:
                self.status.value += (f" (finest stage {run_config.stages[-1].iterations} iterations, not {config.stages[-1].iterations}: "
                                      f"{config.final_stage_min_passes:g} passes over the {acq.n_images} images)")
            self._watch_close()
            self._t0 = time.perf_counter()
        if worker is not None:  # started outside the guard's warning capture (see widget_common._THREADS)
            track_thread(worker, self._done)
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
        """The viewer closes: stop the run and wait (at most 60 s) until its thread has ended."""
        if not self.running:
            return False
        self._closing.set()
        self._stop.set()
        self._done.wait(timeout=60.0)
        return True

    def _on_update(self, update: Update) -> None:
        if self._closing.is_set():
            return
        if update.kind == "started":
            return
        if update.kind == "evaluating":
            self.status.value = "evaluating the fit of every image…"
            return
        snap = update.snapshot
        self.progress.value = snap.global_iteration
        self._time_left.add(snap.stage, snap.iteration, snap.elapsed_s)
        left = self._time_left.seconds_left()
        left_txt = "" if left is None else f", about {_duration(left)} left"
        again = f" again with {', '.join(p.replace('_', ' ') for p in snap.rerun_with)}" if snap.rerun_with else ""
        self.status.value = (f"run #{self._runs}: stage {snap.stage + 1}/{snap.n_stages}{again} (×{snap.factor}), iteration "
                             f"{snap.iteration}/{snap.stage_iterations}; {_duration(snap.elapsed_s)} elapsed{left_txt}")
        self.losses.value = "loss: " + ", ".join(f"{k} {v:.4g}" for k, v in snap.losses.items())
        self.curve.add(snap)
        self.curve_caption.value = "error: " + self.curve.curve.caption()
        if update.ri is not None and self._ri_layer is not None:
            self._show_ri(update.ri)
            self.layer_updates.append((snap.stage, snap.iteration, snap.stage_complete))
            # (no warning capture here: the worker owns the process's warning hook while it runs)
            set_sources(self._viewer, self._acq_layer, snap.sources_um, kind="calibrated", name=self._calibrated_name())

    def _calibrated_name(self) -> str:
        return f"{self._acq_layer.name} sources calibrated #{self._runs}"

    def _show_ri(self, ri: np.ndarray) -> None:
        layer = self._ri_layer
        if layer not in self._viewer.layers:  # the user deleted it: add it again
            acq = acquisition_of(self._acq_layer)
            data, kwargs, _ = ri_layer(ri, acq.optics, self._run_name, owner=self._acq_layer.metadata.get(META_ID))
            self._ri_layer = layer = self._viewer.add_image(data, **kwargs)
        layer.data = ri
        lo = float(self._acq_layer.metadata[META_ACQUISITION].optics.n_background)
        layer.contrast_limits = (lo, max(lo + 1e-4, float(ri.max())))

    def _on_returned(self, result: JobResult) -> None:
        if self._closing.is_set():
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
        self._show_ri(result.ri)
        self._ri_layer.metadata[META_REPORT] = result.report
        set_sources(self._viewer, self._acq_layer, result.sources_um, kind="calibrated", name=self._calibrated_name())
        n = len(result.rec.config.stages)
        fit = (result.report or {}).get("image_fit", {})
        fit_txt = f"; image fit: relative error {fit['image_relative_error']:.3f}" if "image_relative_error" in fit else ""
        if result.cancelled:
            self.progress.value = sum(self._stage_iterations[: result.completed_stages])
            self.status.value = (f"run #{self._runs} cancelled: showing the last complete stage "
                                 f"({result.completed_stages}/{n}){fit_txt}")
        else:
            self.progress.value = self.progress.max
            self.status.value = (f"run #{self._runs} done: {n} stages in {result.rec.elapsed_s:.1f} s on "
                                 f"{result.rec.device}{fit_txt}")

    def _on_error(self, exc: Exception) -> None:
        if self._closing.is_set():
            return
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

    # -- results ------------------------------------------------------------------------------
    def _result(self):
        if self._rec is None or self._report is None:
            raise FDTInputError("result", "there is no finished reconstruction", "press Reconstruct first")
        return self._rec

    def save_result(self, path: str | Path) -> tuple[Path, Path]:
        """Write the RI volume (OME-TIFF) and its report (``.json`` beside it), as ``fdt reconstruct``."""
        from napari_fdt.recon.report import write_result

        rec = self._result()
        report = {**self._report, "output": str(path)}
        return write_result(rec, path, report, overwrite=True)

    def _save_result_dialog(self) -> None:
        from qtpy.QtWidgets import QFileDialog

        suggestion = (self._run_name.split(" (")[0].replace(" #", "_").replace(" ", "_") or "RI") + ".ome.tif"
        path, _ = QFileDialog.getSaveFileName(self.native, "Save RI volume", suggestion, "OME-TIFF (*.ome.tif *.tif)")
        if path:
            self.save_result_in_background(path)

    def save_result_in_background(self, path: str | Path):
        """:meth:`save_result` in a worker thread (the *Save RI…* button); returns the worker, or None if refused.

        A name without ``.tif``/``.tiff`` gets ``.ome.tif`` (what the plugin's reader opens)."""
        from napari_fdt.recon.report import write_result

        path = with_tiff_suffix(path)
        job = None
        with self.feedback.guard():
            rec = self._result()
            report = {**self._report, "output": str(path)}  # this run's, even if another one starts meanwhile
            job = lambda: write_result(rec, path, report, overwrite=True)  # noqa: E731

        def show(written) -> None:
            out, report_file = written
            self.feedback.info(f"wrote {out} and {report_file}")

        if job is None:
            return None
        return self.tasks.start("save", job, show, buttons=(self.save_button,), message=f"writing {path}…")

    def show_comparison(self, index: int):
        """Image ``index`` as the reconstruction predicts it, beside the measured one (computed in a worker; a 2-D layer)."""
        job = None
        with self.feedback.guard():
            rec = self._result()
            index = check_index(index, rec.acquisition.n_images)
            acq_layer = self._acq_layer
            job = lambda: predicted_vs_measured(rec, index)  # noqa: E731

        def show(result) -> None:
            pred, meas = result
            dx = rec.acquisition.optics.pixel_size_um
            owner = acq_layer.metadata.get(META_ID)
            put_layer(self._viewer, (side_by_side(pred, meas), dict(
                name=f"{acq_layer.name} fit: predicted | measured", scale=(dx, dx),
                translate=lateral_translate(rec.acquisition.image_shape, dx), units=UNITS[:2], colormap="gray",
                metadata={META_KIND: "comparison", META_OWNER: owner, "fdt_image": int(index)}), "image"))
            rel = float(np.linalg.norm(pred - meas) / max(float(np.linalg.norm(meas)), 1e-30))
            self.feedback.info(f"image {index}: relative error {rel:.3f} (predicted left, measured right)")

        if job is None:
            return None
        return self.tasks.start("comparison", job, show, buttons=(self.compare_button,),
                                message=f"predicting image {index}…")

    def show_coverage(self):
        """How many sources light each voxel within the pupil, as a volume layer (calibrated sources after a run).

        Computed in a worker thread; returns the worker, or None if refused.
        """
        job = None
        with self.feedback.guard():
            layer = self.layer.value
            acq = acquisition_of(layer)
            if self._rec is not None and layer is self._acq_layer and not self.running:
                sources = self._rec.sources_um()
            else:
                sources = sources_for(self._viewer, layer, acq)
            job = lambda: illumination_coverage(acq.optics, acq.image_shape, sources)  # noqa: E731

        def show(cov: np.ndarray) -> None:
            put_layer(self._viewer, (cov, dict(
                name=f"{layer.name} coverage", scale=volume_scale(acq.optics),
                translate=volume_translate(acq.optics, acq.image_shape), units=UNITS, colormap="viridis",
                contrast_limits=(0, max(1, int(cov.max()))),
                metadata={META_KIND: "coverage", META_OWNER: layer.metadata.get(META_ID)}), "image"))
            self.feedback.info(f"coverage: {int(cov.min())} to {int(cov.max())} sources per voxel; "
                               f"{100 * float((cov == 0).mean()):.0f} % of the voxels unlit")

        if job is None:
            return None
        return self.tasks.start("coverage", job, show, buttons=(self.coverage_button,),
                                message=f"counting the sources that light each voxel of {layer.name}…")

    # -- coherence masks and the command line --------------------------------------------------------
    def preview_masks(self):
        """The coherence masks of all sources for this widget's mask threshold (in a worker thread) → an image stack layer."""
        job = None
        with self.feedback.guard():
            layer = self.layer.value
            acq = acquisition_of(layer)
            sources = sources_for(self._viewer, layer, acq)
            threshold = float(self.mask_threshold.value)
            job = lambda: mask_stack(acq, sources, threshold=threshold)  # noqa: E731

        def show(masks: np.ndarray) -> None:
            o = acq.optics
            put_layer(self._viewer, (masks[:, None], dict(
                name=f"{layer.name} masks", scale=stack_scale(o.pixel_size_um, o.thickness_um),
                translate=stack_translate(acq.image_shape, o.pixel_size_um, o.thickness_um), units=STACK_UNITS,
                axis_labels=STACK_AXIS_LABELS, colormap="green", blending="additive", opacity=0.5, contrast_limits=(0, 1),
                metadata={META_KIND: "masks", META_OWNER: layer.metadata.get(META_ID)}), "image"))
            self.feedback.info(f"masks of {len(masks)} sources at threshold {threshold:g}: "
                               f"{100 * masks.mean():.0f} % of the pixels on average")

        if job is None:
            return None
        return self.tasks.start("masks", job, show, buttons=(self.masks_button,),
                                message=f"computing the masks of {layer.name}…")

    def copy_command(self) -> str | None:
        """The ``fdt reconstruct`` line that repeats this widget's run, to the clipboard; None if refused.

        It needs the acquisition as a folder on disk that holds what the widget uses (optics and sources as
        edited): the layer's folder if they are unchanged, else *Save acquisition…* first. The settings are written
        beside that folder (``<folder>_settings.json``, a new name each time: nothing is overwritten).
        """
        from napari_fdt.data.io import read_acquisition

        with self.feedback.guard():
            layer = self.layer.value
            acq = acquisition_of(layer)
            config = self.config()
            folder = layer.metadata.get(META_PATH)
            if not folder or not (Path(folder) / "acquisition.json").is_file():
                raise FDTInputError("Copy command", f"{layer.name} is not an acquisition folder on disk",
                                    "press Save acquisition… in the FDT acquisition widget first")
            on_disk = read_acquisition(folder)
            sources = sources_for(self._viewer, layer, acq, required=False)
            same_sources = (sources is None and on_disk.sources_um is None) or (
                sources is not None and on_disk.sources_um is not None
                and np.allclose(sources, on_disk.sources_um, rtol=0, atol=1e-9))
            if on_disk.optics != acq.optics or not same_sources:
                raise FDTInputError("Copy command", f"the optics or sources of {layer.name} differ from {folder}",
                                    "press Save acquisition… in the FDT acquisition widget to write them, then copy again")
            folder = Path(folder)
            settings = unique_path(folder.with_name(f"{folder.name}_settings.json"))
            config.save(settings)
            out = unique_path(folder.with_name(f"{folder.name}_RI.ome.tif"))
            command = format_command(reconstruct_command(folder, out, settings, device=self.device.value))
            self.last_command = command
            try:
                from qtpy.QtWidgets import QApplication

                QApplication.clipboard().setText(command)
            except Exception:  # noqa: BLE001 (no clipboard on this display: the line is shown below anyway)
                pass
            self.feedback.info(f"copied: {command}")
            return command
        return None
