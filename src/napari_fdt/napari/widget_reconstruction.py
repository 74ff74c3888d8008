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
from napari_fdt.napari.compute import check_index, illumination_coverage, predicted_vs_measured
from napari_fdt.napari.job import JobResult, Update, reconstruction_job
from napari_fdt.napari.layers import (
    META_ID,
    META_KIND,
    META_OWNER,
    META_PATH,
    META_REPORT,
    UNITS,
    lateral_translate,
    ri_layer,
    side_by_side,
    volume_scale,
    volume_translate,
)
from napari_fdt.napari.schema_widgets import schema_widget
from napari_fdt.napari.settings import format_stages, merge_config
from napari_fdt.napari.widget_common import (
    BackgroundTasks,
    CloseWatcher,
    Feedback,
    acquisition_layer_choices,
    acquisition_of,
    follow_layers,
    put_layer,
    refresh_layer_choice,
    set_sources,
    sources_for,
    track_thread,
)
from napari_fdt.napari.widget_curve import ErrorCurveWidget
from napari_fdt.recon.config import SolverConfig, load_config

if TYPE_CHECKING:  # pragma: no cover
    import napari

__all__ = ["ReconstructionWidget", "UPDATE_INTERVAL_S", "device_choices"]

#: Least time between two updates of the RI layer within a stage, s (stage ends always update).
UPDATE_INTERVAL_S = 0.5

#: Settings the widget edits, by widget attribute (= SolverConfig field).
_FIELDS = ("stages", "coarse_model", "batch_size", "l1_l2_total", "ssim_weight", "tv_xy_weight", "tv_z_weight",
           "calibrate_sources", "calibrate_gain", "calibrate_source_depth", "calibrate_pixel_size",
           "calibrate_slice_spacing", "calibration_from_stage", "coherence", "mask_threshold", "seed", "snapshot_every",
           "validation_fraction", "early_stopping")


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
        self.calibration_from_stage = f("calibration_from_stage", "calibrate from stage")
        self.coherence = f("coherence", "coherence")
        self.mask_threshold = f("mask_threshold", "mask threshold", step=0.05)
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
        self.compare_index = SpinBox(label="image", min=0, max=0)
        self.compare_button = PushButton(text="Predicted vs measured", enabled=False)
        self.coverage_button = PushButton(text="Illumination coverage")
        self.feedback = Feedback()
        self.tasks = BackgroundTasks(napari_viewer, self.feedback, self.native, refresh=lambda: self._set_running(self.running))
        self.extend([
            self.layer, Label(value="<b>Solver</b>"), self.stages, self.coarse_model, self.batch_size,
            self.l1_l2_total, self.ssim_weight, self.tv_xy_weight, self.tv_z_weight,
            Label(value="<b>Self-calibration</b>"), self.calibrate_sources, self.calibrate_gain,
            self.calibrate_source_depth, self.calibrate_pixel_size, self.calibrate_slice_spacing,
            self.calibration_from_stage, Label(value="<b>Coherence and run</b>"), self.coherence, self.mask_threshold,
            self.device, self.seed, self.snapshot_every, Label(value="<b>Validation</b>"), self.validation_fraction,
            self.early_stopping,
            Container(widgets=[self.save_settings_button, self.load_settings_button], layout="horizontal", labels=False),
            Container(widgets=[self.run_button, self.cancel_button], layout="horizontal", labels=False),
            self.progress, self.status, self.losses, self.curve_caption,
            Label(value="<b>Results</b>"), self.save_button, self.compare_index, self.compare_button,
            self.coverage_button, self.feedback.label,
        ])
        for w in (self.status, self.losses, self.curve_caption):
            w.native.setWordWrap(True)
        # the error curve sits under its caption (a plain Qt widget in the magicgui container's layout, after the
        # caption's labelled row)
        layout = self.native.layout()
        layout.insertWidget(layout.indexOf(self.curve_caption.native.parentWidget()) + 1, self.curve)
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
        self._task_id = None
        self._close_watcher = None
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

    # -- settings -----------------------------------------------------------------------------
    def config(self) -> SolverConfig:
        """The settings in the widget over the last loaded ones, checked (raises :class:`FDTInputError`)."""
        return merge_config(self._base, {name: getattr(self, name).value for name in _FIELDS})

    def set_config(self, config: SolverConfig) -> None:
        """Show ``config`` in the widget; settings it does not show are kept for saving and running."""
        self._base = config
        for name in _FIELDS:
            value = getattr(config, name)
            getattr(self, name).value = format_stages(value) if name == "stages" else value

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
        """Check everything, then start the reconstruction in a worker thread."""
        from napari.qt.threading import create_worker
        from superqt.utils import GeneratorWorker  # without napari's relay: errors and warnings are shown below

        if self.running:
            return
        worker = None
        with self.feedback.guard():
            layer = self.layer.value
            acq = acquisition_of(layer)
            config = self.config()
            sources = sources_for(self._viewer, layer, acq, required=False)
            device = self.device.value
            from napari_fdt.device import resolve_device

            resolve_device(device)
            self._acq_layer = layer
            self._rec, self._report, self.cancelled = None, None, False
            self.layer_updates = []
            stop, done, closing = threading.Event(), threading.Event(), threading.Event()
            n_b = acq.optics.n_background
            data, kwargs, kind = ri_layer(np.full((acq.optics.n_slices, *acq.image_shape), n_b, np.float32),
                                          acq.optics, f"{layer.name} RI", owner=layer.metadata.get(META_ID))
            kwargs["contrast_limits"] = (n_b, n_b + 0.5 * config.delta_n_max)
            self._ri_layer = put_layer(self._viewer, (data, kwargs, kind))
            self._ri_layer.metadata.pop(META_REPORT, None)
            self._ri_layer.contrast_limits = kwargs["contrast_limits"]
            worker = create_worker(
                reconstruction_job, acq, config, device=device, initial_sources_um=sources, stop=stop,
                done=done, closing=closing, min_interval_s=UPDATE_INTERVAL_S,
                acquisition_path=layer.metadata.get(META_PATH), _start_thread=False, _ignore_errors=True,
                _worker_class=GeneratorWorker,
            )
            worker.yielded.connect(self._on_update)
            worker.returned.connect(self._on_returned)
            worker.errored.connect(self._on_error)
            worker.warned.connect(self._on_warning)
            worker.finished.connect(self._on_finished)
            self._worker = worker
            self._stop, self._done, self._closing = stop, done, closing
            self.progress.max = max(1, config.total_iterations)
            self.progress.value = 0
            self.curve.reset(config.total_iterations)
            self.curve_caption.value = ""
            self._set_running(True)
            self.feedback.info(f"reconstructing {layer.name} on {device}…")
            self._watch_close()
            self._t0 = time.perf_counter()
        if worker is not None:  # started outside the guard's warning capture (see _widget_common._THREADS)
            track_thread(worker, self._done)
            worker.start()

    def cancel(self) -> None:
        """Stop at the next iteration; the RI layer then shows the last complete stage."""
        if self.running:
            self._stop.set()
            self.status.value = "cancelling at the next iteration…"

    def _set_running(self, running: bool) -> None:
        self.run_button.enabled = not running
        self.cancel_button.enabled = running
        self.load_settings_button.enabled = not running
        has_result = (not running) and self._rec is not None and self._report is not None
        self.save_button.enabled = has_result and not self.tasks.is_running("save")
        self.compare_button.enabled = has_result and not self.tasks.is_running("comparison")
        self.coverage_button.enabled = not self.tasks.is_running("coverage")

    def _watch_close(self) -> None:
        """Stop the run when the viewer closes: napari's task status (asks before closing) or a close filter."""
        window = getattr(self._viewer, "window", None)
        register = getattr(window, "_register_task_status", None)
        if register is not None:
            from napari.utils.task_status import Status

            self._task_id = register("napari-fdt", Status.BUSY, "reconstruction running", cancel_callback=self._on_viewer_closing)
        elif self._close_watcher is None:
            self._close_watcher = CloseWatcher(self.native.window(), self._on_viewer_closing)

    def _task_status(self, status: str, text: str = "") -> None:
        window = getattr(self._viewer, "window", None)
        update = getattr(window, "_update_task_status", None)
        if update is not None and self._task_id is not None:
            from napari.utils.task_status import Status

            update(self._task_id, getattr(Status, status), text)

    def _on_viewer_closing(self) -> bool:
        """The viewer closes: stop the thread and wait (at most 60 s) until it has ended.

        napari itself asks its workers to quit on close (``worker.quit()``); the worker then drops the
        generator at its next yield. Either way the thread ends within one iteration; a dropped job
        generator is closed here so that its clean-up runs now.
        """
        if not self.running:
            return False
        self._closing.set()
        self._stop.set()
        worker = self._worker
        deadline = time.monotonic() + 60.0
        while not self._done.is_set() and time.monotonic() < deadline:
            if worker is not None and not worker.is_running:
                gen = getattr(worker, "_gen", None)  # dropped by worker.quit(): close it here
                if gen is not None:
                    gen.close()
                self._done.set()  # the job can no longer run
                break
            time.sleep(0.01)
        self._done.wait(timeout=max(0.0, deadline - time.monotonic()))
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
        self.status.value = (f"stage {snap.stage + 1}/{snap.n_stages} (×{snap.factor}), iteration "
                             f"{snap.iteration}/{snap.stage_iterations}; {snap.elapsed_s:.0f} s elapsed, "
                             f"about {snap.eta_s:.0f} s left")
        self.losses.value = "loss: " + ", ".join(f"{k} {v:.4g}" for k, v in snap.losses.items())
        self.curve.add(snap)
        self.curve_caption.value = "error: " + self.curve.curve.caption()
        if update.ri is not None and self._ri_layer is not None:
            self._show_ri(update.ri)
            self.layer_updates.append((snap.stage, snap.iteration, snap.stage_complete))
            # (no warning capture here: the worker owns the process's warning hook while it runs)
            set_sources(self._viewer, self._acq_layer, snap.sources_um)

    def _show_ri(self, ri: np.ndarray) -> None:
        layer = self._ri_layer
        if layer not in self._viewer.layers:  # the user deleted it: add it again
            acq = acquisition_of(self._acq_layer)
            self._ri_layer = layer = put_layer(self._viewer, ri_layer(ri, acq.optics, f"{self._acq_layer.name} RI",
                                                                      owner=self._acq_layer.metadata.get(META_ID)))
        layer.data = ri
        lo = float(self._acq_layer.metadata["fdt_acquisition"].optics.n_background)
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
            self._ri_layer = None
            self._rec = None
            self.status.value = "cancelled before the first stage ended: nothing kept"
            self._task_status("CANCELLED")
            return
        self._report = result.report
        self._show_ri(result.ri)
        self._ri_layer.metadata[META_REPORT] = result.report
        set_sources(self._viewer, self._acq_layer, result.sources_um)
        n = len(result.rec.config.stages)
        fit = (result.report or {}).get("image_fit", {})
        fit_txt = f"; image fit: relative error {fit['image_relative_error']:.3f}" if "image_relative_error" in fit else ""
        if result.cancelled:
            self.status.value = f"cancelled: showing the last complete stage ({result.completed_stages}/{n}){fit_txt}"
            self._task_status("CANCELLED")
        else:
            self.progress.value = self.progress.max
            self.status.value = f"done: {n} stages in {result.rec.elapsed_s:.1f} s on {result.rec.device}{fit_txt}"
            self._task_status("COMPLETED")

    def _on_error(self, exc: Exception) -> None:
        self._task_status("FAILED", str(exc))
        if self._closing.is_set():
            return
        self.status.value = "failed"
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

        path, _ = QFileDialog.getSaveFileName(self.native, "Save RI volume", "RI.ome.tif", "OME-TIFF (*.ome.tif *.tif)")
        if path:
            self.save_result_in_background(path)

    def save_result_in_background(self, path: str | Path):
        """:meth:`save_result` in a worker thread (the *Save RI…* button); returns the worker, or None if refused."""
        from napari_fdt.recon.report import write_result

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
