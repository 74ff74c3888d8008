"""The FDT acquisition widget: optics, source positions, a forward preview, and Save acquisition.

* **Optics** are text fields, **empty until the file or the user gives them**: prefilled from the layer's
  acquisition, else from the optics a reader found in the file (``metadata["fdt_file_optics"]``), else left
  empty. What is typed is kept per layer (``metadata["fdt_optics_entries"]``). The values are checked as they are
  typed (:func:`napari_fdt.napari.settings.optics_from_entries`: a missing field named, a unit mistake such as
  ``635 looks like nm`` refused); Fit sources and the preview stay disabled until they are complete and valid.
  *Apply optics* (and any action) stores them on the layer, which gets its physical scale and its image index on
  an axis of its own (``docs/napari.md``); the view is reframed.
* **Fit sources**: the paper's per-image 2-D Gaussian fit (:func:`napari_fdt.recon.calibration.source_fit.initial_sources`),
  at the depth typed in *source depth* (empty: estimated from the image widths, a lower bound). The result is an
  editable 3-D points layer at ``(z, y, x) = (−depth, y, x)`` µm; the reconstruction starts from the points as edited.
* **Forward preview**: one image as the forward model predicts it for the current optics, sources and
  RI (this acquisition's latest RI layer if there is one, else the homogeneous medium), beside the measured one.
* **Save acquisition…** writes a format-v1 folder (``acquisition.json`` + ``images.tif``) with the optics and the
  sources as edited (:func:`napari_fdt.data.io.write_acquisition`), never over an existing path.

The fit, the preview and the save run in worker threads (:class:`~napari_fdt.napari.widgets.widget_tasks.BackgroundTasks`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from magicgui.widgets import ComboBox, Container, Label, LineEdit, PushButton, SpinBox

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.errors import FDTInputError
from napari_fdt.napari.jobs.compute import check_index, forward_preview
from napari_fdt.napari.layers import (
    META_ACQUISITION,
    META_FILE_OPTICS,
    META_ID,
    META_KIND,
    META_OPTICS_ENTRIES,
    META_OWNER,
    META_PATH,
    UNITS,
    lateral_translate,
    side_by_side,
    stack_images,
)
from napari_fdt.napari.settings import OPTICS_LABELS, format_entry, missing_optics, optics_from_entries
from napari_fdt.napari.widgets.widget_layers import (
    acquisition_layer_choices,
    adopt_layer,
    find_layer,
    follow_layers,
    no_layer,
    put_layer,
    refresh_layer_choice,
    set_sources,
    sources_for,
)
from napari_fdt.napari.widgets.widget_layout import follow_ndisplay, sections_panel, tighten
from napari_fdt.napari.widgets.widget_tasks import BackgroundTasks, Feedback, watch_wrong_reader
from napari_fdt.physics.optics import OPTICS_FIELDS, Optics

if TYPE_CHECKING:  # pragma: no cover
    import napari

__all__ = ["AcquisitionWidget", "OPTICS_TIPS"]

#: Tooltips of the optics fields (where to find the value), each starting with the field's name in the files and the
#: API (``acquisition.json``, :class:`~napari_fdt.physics.optics.Optics`); the labels are plain words
#: (:data:`napari_fdt.napari.settings.OPTICS_LABELS`).
OPTICS_TIPS = {
    "wavelength_um": "wavelength_um: vacuum emission wavelength of the fluorophore, µm (e.g. 0.635 for 635 nm)",
    "n_background": "n_background: the refractive index of the immersion medium around the sample (water 1.33, oil 1.518)",
    "na": "na: numerical aperture of the detection objective (below the medium refractive index)",
    "pixel_size_um": "pixel_size_um: camera pixel size divided by the magnification, µm in the sample "
                     "(e.g. 6.5 µm pixels at 40×: 0.1625)",
    "n_slices": "n_slices: number of slices of the RI volume to reconstruct",
    "slice_spacing_um": "slice_spacing_um: thickness of one slice of the RI volume, µm",
    "image_plane_um": "image_plane_um: camera focal plane below the volume's top face, µm (empty: 0, the top face)",
}


class AcquisitionWidget(Container):
    """Dock widget: optics, sources and forward preview of one image stack, and Save acquisition."""

    def __init__(self, napari_viewer: "napari.viewer.Viewer") -> None:
        super().__init__(labels=False)
        self._viewer = napari_viewer
        self.layer = ComboBox(label="images", choices=self._choices,
                              tooltip="the image stack (N, H, W), opened by any reader")
        for name in OPTICS_FIELDS:
            setattr(self, name, LineEdit(name=name, label=OPTICS_LABELS[name], value="", tooltip=OPTICS_TIPS[name]))
        self.optics_state = Label(value="")
        self.optics_state.native.setWordWrap(True)
        self.apply_button = PushButton(text="Apply optics")
        self.save_acquisition_button = PushButton(text="Save acquisition…")
        self.depth_um = LineEdit(label="source depth (µm)", value="",
                                 tooltip="depth_um: common depth of the sources below the volume, µm; empty: estimated from the "
                                         "image widths (a lower bound when the light discs fill the images)")
        self.fit_button = PushButton(text="Fit sources")
        self.file_sources_button = PushButton(text="Sources from file")
        self.image_index = SpinBox(label="image", min=0, max=0, tooltip="index of the image to predict (0: the first)")
        self.preview_button = PushButton(text="Forward preview")
        self.feedback = Feedback()
        optics_box = Container(widgets=[*(getattr(self, n) for n in OPTICS_FIELDS), self.optics_state,
                                        Container(widgets=[self.apply_button, self.save_acquisition_button],
                                                  layout="horizontal", labels=False)])
        sources_box = Container(widgets=[self.depth_um, Container(widgets=[self.fit_button, self.file_sources_button],
                                                                  layout="horizontal", labels=False)])
        preview_box = Container(widgets=[self.image_index, self.preview_button])
        self.extend([Container(widgets=[self.layer]), self.feedback.label])
        self.sections = sections_panel([("Optics", optics_box, True), ("Sources", sources_box, True),
                                        ("Forward preview", preview_box, False)], height_px=600)
        tighten(self, (4, 2, 4, 2))
        from qtpy.QtWidgets import QSizePolicy

        # no taller than its content: the height left in the dock area goes to the reconstruction widget
        self.native.setSizePolicy(QSizePolicy.Policy.Preferred, QSizePolicy.Policy.Maximum)
        layout = self.native.layout()
        layout.insertWidget(1, self.sections, 1)
        self.tasks = BackgroundTasks(napari_viewer, self.feedback, self.native, refresh=self._update_buttons)
        self._shown = None
        self._filling = False
        self.layer.changed.connect(self._on_layer_changed)
        for name in OPTICS_FIELDS:
            getattr(self, name).changed.connect(self._on_optics_edited)
        self.apply_button.changed.connect(self.apply_optics)
        self.save_acquisition_button.changed.connect(self._save_acquisition_dialog)
        self.fit_button.changed.connect(self.fit_sources)
        self.file_sources_button.changed.connect(self.sources_from_file)
        self.preview_button.changed.connect(self.preview_image)
        watch_wrong_reader(self.feedback)
        follow_ndisplay(napari_viewer)
        follow_layers(napari_viewer, self.layer, self._refresh)
        self._update_buttons()

    # -- layer selection ----------------------------------------------------------------------
    def _choices(self, _widget=None) -> list[tuple[str, object]]:
        return acquisition_layer_choices(self._viewer)

    def _refresh(self, _event=None) -> None:
        refresh_layer_choice(self.layer)
        if self.layer.value is not self._shown:
            self._on_layer_changed(self.layer.value)

    def entries(self) -> dict[str, str]:
        """The optics fields' text, field → text."""
        return {name: str(getattr(self, name).value or "").strip() for name in OPTICS_FIELDS}

    def _set_entries(self, values: dict[str, str]) -> None:
        self._filling = True
        try:
            for name in OPTICS_FIELDS:
                getattr(self, name).value = values.get(name, "")
        finally:
            self._filling = False
        self._update_buttons()

    def _layer_entries(self, layer) -> dict[str, str]:
        """What the fields show for ``layer``: typed for it, else its acquisition's optics, else the file's, else empty."""
        typed = layer.metadata.get(META_OPTICS_ENTRIES)
        if typed is not None:
            return dict(typed)
        acq = layer.metadata.get(META_ACQUISITION)
        if acq is not None:
            return {k: format_entry(v) for k, v in acq.optics.to_dict().items()}
        found = layer.metadata.get(META_FILE_OPTICS) or {}
        return {k: format_entry(found.get(k)) for k in OPTICS_FIELDS}

    def _on_layer_changed(self, layer=None) -> None:
        self._shown = layer
        self.feedback.info("")
        if layer is None:
            self._set_entries({})
            return
        self._set_entries(self._layer_entries(layer))
        acq = layer.metadata.get(META_ACQUISITION)
        self.depth_um.value = ("" if acq is None or acq.sources_um is None
                               else format_entry(round(float(np.median(acq.sources_um[:, 2])), 3)))
        n = int(np.shape(layer.data)[0])
        self.image_index.max = max(0, n - 1)
        h, w = np.shape(layer.data)[-2:]
        if acq is not None:
            self.feedback.info(f"{layer.name}: {n} images of {h}×{w} px")
        else:
            missing = missing_optics(self.entries())
            self.feedback.info(f"{layer.name}: {n} images of {h}×{w} px without optics"
                               + (f": enter {', '.join(missing)} and press Apply optics" if missing else ""))

    def _on_optics_edited(self, _value=None) -> None:
        if self._filling:
            return
        layer = self.layer.value
        if layer is not None:
            layer.metadata[META_OPTICS_ENTRIES] = self.entries()
        if self.feedback.last_error is not None:  # a stale error about the optics goes once they are edited
            self.feedback.info("")
        self._update_buttons()

    def optics_problem(self) -> str | None:
        """Why the fields do not give optics yet (missing or refused), or None when they do."""
        try:
            optics_from_entries(self.entries())
        except FDTInputError as exc:
            return str(exc)
        return None

    def _update_buttons(self) -> None:
        problem = None if self.layer.value is None else self.optics_problem()
        self.optics_state.value = "" if problem is None else problem
        self.optics_state.native.setStyleSheet("color: #ffb040;" if problem else "")
        ready = self.layer.value is not None and problem is None
        self.fit_button.enabled = ready and not self.tasks.is_running("fit sources")
        self.preview_button.enabled = ready and not self.tasks.is_running("forward preview")
        self.file_sources_button.enabled = ready
        self.save_acquisition_button.enabled = ready and not self.tasks.is_running("save acquisition")

    # -- actions ------------------------------------------------------------------------------
    def optics(self) -> Optics:
        """The optics in the fields, checked (raises :class:`FDTInputError` naming the field's label)."""
        return optics_from_entries(self.entries())

    def current_acquisition(self) -> tuple[object, Acquisition]:
        """(layer, acquisition) with the optics of the fields applied to the layer (metadata, scale, own image axis)."""
        layer = self.layer.value
        if layer is None:
            raise no_layer()
        optics = self.optics()
        acq = layer.metadata.get(META_ACQUISITION)
        if acq is None or acq.optics != optics or np.ndim(layer.data) != 4:
            if acq is None:
                acq = Acquisition(images=np.ascontiguousarray(stack_images(layer.data)), optics=optics)
            elif acq.optics != optics:
                acq = Acquisition(images=acq.images, optics=optics, sources_um=acq.sources_um, extra=acq.extra)
            entries = self.entries()
            new = adopt_layer(self._viewer, layer, acq)
            new.metadata[META_OPTICS_ENTRIES] = entries
            if new is not layer:
                self._shown = new
                self.layer.value = new
            layer = new
            self._viewer.reset_view()
        return layer, acq

    def apply_optics(self) -> None:
        """Check the optics and store them on the layer."""
        with self.feedback.guard():
            layer, acq = self.current_acquisition()
            o = acq.optics
            self.feedback.info(f"optics applied to {layer.name}: volume {o.n_slices} × {o.slice_spacing_um:g} µm, "
                               f"pixel {o.pixel_size_um:g} µm")
        self._update_buttons()

    def _depth(self) -> float | None:
        text = str(self.depth_um.value or "").strip()
        if not text:
            return None
        try:
            depth = float(text.replace(",", "."))
        except ValueError:
            raise FDTInputError("source depth (µm)", f"{text!r} is not a number",
                                "type the depth in µm, or leave it empty to estimate it") from None
        if not depth > 0:
            raise FDTInputError("source depth (µm)", f"{depth:g} is not above 0",
                                "the sources lie below the volume: give a positive depth, or leave it empty")
        return depth

    def fit_sources(self):
        """2-D Gaussian fit of every image (in a worker thread) → the sources points layer."""
        from napari_fdt.recon.calibration.source_fit import initial_sources

        job = None
        with self.feedback.guard():
            depth = self._depth()
            layer, acq = self.current_acquisition()
            job = lambda: initial_sources(acq, depth_um=depth, device="cpu")  # noqa: E731

        def show(result) -> None:
            sources, report = result
            self._check_still_open(layer)
            set_sources(self._viewer, layer, sources)
            reliable = int(np.sum(report["lateral_reliable"]))
            d = float(np.median(sources[:, 2]))
            if depth is None:
                how = (f"depth {d:.1f} µm estimated from the image widths (a lower bound when the discs fill the "
                       f"images: if you know the depth, type it in source depth (µm) and fit again)")
            else:
                how = f"depth {d:.1f} µm as typed"
            self.feedback.info(f"fitted {len(sources)} sources ({reliable} reliable), {how}; edit the points to correct them")

        if job is None:
            return None
        return self.tasks.start("fit sources", job, show, buttons=(self.fit_button,),
                                message=f"fitting the sources of {layer.name}…")

    def _check_still_open(self, layer) -> None:
        if layer not in self._viewer.layers:
            raise FDTInputError("images", f"{layer.name} was closed while the result was computed", "open it again")

    def sources_from_file(self) -> None:
        """The acquisition's own ``sources_um`` → the sources points layer."""
        with self.feedback.guard():
            layer, acq = self.current_acquisition()
            if acq.sources_um is None:
                raise FDTInputError("sources", f"{layer.name} has none in its file", "press Fit sources")
            set_sources(self._viewer, layer, acq.sources_um)
            self.feedback.info(f"{len(acq.sources_um)} sources from the file")

    def preview_image(self):
        """Predicted and measured image ``image`` side by side (computed in a worker thread; a 2-D layer)."""
        job = None
        with self.feedback.guard():
            layer, acq = self.current_acquisition()
            sources = sources_for(self._viewer, layer, acq)
            ri_layer = find_layer(self._viewer, layer.metadata[META_ID], "ri")
            # a copy: the RI layer may change (a running reconstruction) while the worker reads it
            delta_n = None if ri_layer is None else np.array(ri_layer.data, dtype=np.float32) - np.float32(acq.optics.n_background)
            index = check_index(self.image_index.value, acq.n_images)
            medium = "homogeneous medium" if ri_layer is None else ri_layer.name
            job = lambda: forward_preview(acq, sources, index, delta_n)  # noqa: E731

        def show(result) -> None:
            pred, meas, _ = result
            self._check_still_open(layer)
            dx = acq.optics.pixel_size_um
            first = find_layer(self._viewer, layer.metadata[META_ID], "preview") is None
            put_layer(self._viewer, (side_by_side(pred, meas), dict(
                name=f"{layer.name} preview: model | measured", scale=(dx, dx),
                translate=lateral_translate(acq.image_shape, dx), units=UNITS[:2], colormap="gray",
                metadata={META_KIND: "preview", META_OWNER: layer.metadata[META_ID], "fdt_image": index}), "image"))
            if first:
                self._viewer.reset_view()
            rel = float(np.linalg.norm(pred - meas) / max(float(np.linalg.norm(meas)), 1e-30))
            self.feedback.info(f"image {index} ({medium}): relative difference {rel:.3f} after a least-squares gain")

        if job is None:
            return None
        return self.tasks.start("forward preview", job, show, buttons=(self.preview_button,),
                                message=f"predicting image {index} of {layer.name}…")

    # -- save acquisition -----------------------------------------------------------------------
    def acquisition_to_save(self) -> Acquisition:
        """The acquisition as shown: the layer's images, the optics in the fields, the sources as edited (if any)."""
        layer, acq = self.current_acquisition()
        sources = sources_for(self._viewer, layer, acq, required=False)
        return Acquisition(images=acq.images, optics=acq.optics, sources_um=sources, extra=acq.extra)

    def save_acquisition(self, path: str | Path):
        """Write the acquisition as a format-v1 folder at ``path`` (in a worker thread; an existing path is refused)."""
        from napari_fdt.data.io import write_acquisition

        job = None
        with self.feedback.guard():
            path = Path(path)
            if path.exists():
                raise FDTInputError("Save acquisition", f"{path} exists", "choose a new folder name: nothing is overwritten")
            acq = self.acquisition_to_save()
            job = lambda: write_acquisition(acq, path, overwrite=False)  # noqa: E731

        layer = self.layer.value

        def show(written) -> None:
            if layer in self._viewer.layers:  # the layer now is what the folder holds (Copy command runs on it)
                layer.metadata[META_PATH] = str(written)
            note = "" if acq.sources_um is not None else " (no sources yet: fit them before reconstructing from it)"
            self.feedback.info(f"wrote the acquisition folder {written}{note}")

        if job is None:
            return None
        return self.tasks.start("save acquisition", job, show, buttons=(self.save_acquisition_button,),
                                message=f"writing {path}…")

    def _save_acquisition_dialog(self) -> None:
        from qtpy.QtWidgets import QFileDialog

        layer = self.layer.value
        suggestion = f"{layer.name}_acquisition" if layer is not None else "acquisition"
        path, _ = QFileDialog.getSaveFileName(self.native, "Save acquisition folder", suggestion, "Acquisition folder (*)")
        if path:
            self.save_acquisition(path)
