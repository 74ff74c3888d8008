"""The reconstruction widget's actions on a run's result and on the acquisition: save the RI, predicted vs measured,
illumination coverage, coherence masks and the command line that repeats the run.

A mixin of :class:`~napari_fdt.napari.widgets.widget_reconstruction.ReconstructionWidget` (one concern per module); it uses the
widget's ``_viewer``, ``feedback``, ``tasks`` (:class:`~napari_fdt.napari.widgets.widget_tasks.BackgroundTasks`), ``layer``,
``mask_threshold``, ``device``, ``config()``, ``running`` and the last run's ``_rec`` (a
:class:`~napari_fdt.napari.jobs.remote_job.RunResult`), ``_report``, ``_run_name`` and ``_acq_layer``. Each action computes
in a worker thread, its button disabled meanwhile; no physics here (:mod:`napari_fdt.napari.jobs.compute`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from napari_fdt.errors import FDTInputError
from napari_fdt.napari.jobs.compute import check_index, illumination_coverage, mask_stack
from napari_fdt.napari.layers import (
    META_ID,
    META_KIND,
    META_OWNER,
    META_PATH,
    STACK_AXIS_LABELS,
    STACK_UNITS,
    UNITS,
    lateral_translate,
    side_by_side,
    stack_scale,
    stack_translate,
    volume_scale,
    volume_translate,
)
from napari_fdt.napari.widgets.widget_layers import acquisition_of, put_layer, sources_for
from napari_fdt.recon.settings.command import command_for_folder

__all__ = ["ResultActions", "with_tiff_suffix"]


def with_tiff_suffix(path: str | Path) -> Path:
    """``path`` with ``.ome.tif`` added when it has no ``.tif``/``.tiff`` suffix (``my_cells_RI`` → ``my_cells_RI.ome.tif``)."""
    path = Path(path)
    return path if path.suffix.lower() in (".tif", ".tiff") else path.with_name(path.name + ".ome.tif")


class ResultActions:
    """Save, compare, coverage, masks and the command line of the reconstruction widget (see the module's doc)."""

    # -- results ------------------------------------------------------------------------------
    def _result(self):
        if self._rec is None or self._report is None:
            raise FDTInputError("result", "there is no finished reconstruction", "press Reconstruct first")
        return self._rec

    def save_result(self, path: str | Path) -> tuple[Path, Path]:
        """Write the RI volume (OME-TIFF) and its report (``.json`` beside it), as ``fdt reconstruct``."""
        from napari_fdt.recon.run.report import write_result

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
        from napari_fdt.recon.run.report import write_result

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
            job = lambda: rec.predicted_vs_measured(index)  # noqa: E731 (in the run's computation process)

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
        with self.feedback.guard():
            layer = self.layer.value
            acq = acquisition_of(layer)
            sources = sources_for(self._viewer, layer, acq, required=False)
            command, _ = command_for_folder(layer.metadata.get(META_PATH), acq.optics, sources, self.config(),
                                            device=self.device.value, name=layer.name)
            self.last_command = command
            try:
                from qtpy.QtWidgets import QApplication

                QApplication.clipboard().setText(command)
            except Exception:  # noqa: BLE001 (no clipboard on this display: the line is shown below anyway)
                pass
            self.feedback.info(f"copied: {command}")
            return command
        return None
