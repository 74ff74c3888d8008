"""The FDT acquisition widget: optics, source positions, coherence masks and a forward preview.

* **Optics** are prefilled from the selected layer's acquisition (or left at defaults for a bare TIFF
  stack) and checked by :class:`~napari_fdt.physics.optics.Optics`; its message appears in the widget and as a
  napari notification, and the widget stays usable. *Apply optics* stores them on the layer (which then
  gets its physical scale).
* **Fit sources**: the paper's per-image 2-D Gaussian fit (:func:`napari_fdt.recon.source_fit.initial_sources`),
  with an optional common depth. The result is an editable 3-D points layer at ``(z, y, x) =
  (−depth, y, x)`` µm (``docs/napari.md``); the reconstruction starts from the points as edited.
* **Preview masks**: the solver's coherence masks of every source, as an image stack layer.
* **Forward preview**: one image as the forward model predicts it for the current optics, sources and
  RI (this acquisition's RI layer if there is one, else the homogeneous medium), beside the measured one.

The fit and the two previews compute in worker threads (:class:`~napari_fdt.napari.widget_common.BackgroundTasks`):
the GUI thread only checks the inputs and, when the result comes back, adds the layer. Each action's button
is disabled while it runs; each method returns the worker (None when the inputs were refused).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from magicgui.widgets import ComboBox, Container, FloatSpinBox, Label, PushButton, SpinBox

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.napari.compute import check_index, forward_preview, mask_stack
from napari_fdt.napari.layers import (
    META_ACQUISITION,
    META_ID,
    META_KIND,
    META_NEEDS_OPTICS,
    META_OWNER,
    UNITS,
    lateral_translate,
    side_by_side,
    stack_scale,
    stack_translate,
)
from napari_fdt.napari.schema_widgets import schema_widget
from napari_fdt.napari.widget_common import (
    BackgroundTasks,
    Feedback,
    acquisition_layer_choices,
    find_layer,
    follow_layers,
    no_layer,
    put_layer,
    refresh_layer_choice,
    set_sources,
    sources_for,
)
from napari_fdt.physics.optics import OPTICS_FIELDS, Optics
from napari_fdt.recon.config import SolverConfig

if TYPE_CHECKING:  # pragma: no cover
    import napari

__all__ = ["AcquisitionWidget"]

#: Defaults shown for a stack without optics: the schema's example values (those of ``fdt simulate``).
DEFAULT_OPTICS = Optics.examples()


class AcquisitionWidget(Container):
    """Dock widget: optics, sources, masks and forward preview of one acquisition layer."""

    def __init__(self, napari_viewer: "napari.viewer.Viewer") -> None:
        super().__init__(labels=True)
        self._viewer = napari_viewer
        self.layer = ComboBox(label="images", choices=self._choices)
        # Optics fields from the schema of Optics, with wide ranges on purpose (clamp=False): the core checks the
        # values and explains what is wrong.
        def optic(name: str, label: str, step: float | None = None):
            return schema_widget(Optics, name, label=label, step=step, clamp=False)

        self.wavelength_um = optic("wavelength_um", "wavelength (µm)", 0.001)
        self.n_background = optic("n_background", "n background", 0.001)
        self.na = optic("na", "NA", 0.01)
        self.pixel_size_um = optic("pixel_size_um", "pixel size (µm)", 0.001)
        self.n_slices = optic("n_slices", "slices")
        self.slice_spacing_um = optic("slice_spacing_um", "slice spacing (µm)", 0.01)
        self.image_plane_um = optic("image_plane_um", "image plane (µm)", 0.01)
        self.apply_button = PushButton(text="Apply optics")
        self.depth_um = FloatSpinBox(label="source depth (µm)", min=0.0, max=1e5, step=0.1,
                                     tooltip="common depth of the sources below the volume; 0: estimate it from the image widths")
        self.fit_button = PushButton(text="Fit sources")
        self.file_sources_button = PushButton(text="Sources from file")
        self.mask_threshold = schema_widget(SolverConfig, "mask_threshold", label="mask threshold", step=0.05)
        self.masks_button = PushButton(text="Preview masks")
        self.image_index = SpinBox(label="image", min=0, max=0)
        self.preview_button = PushButton(text="Forward preview")
        self.feedback = Feedback()
        self.extend([
            self.layer, Label(value="<b>Optics</b>"), self.wavelength_um, self.n_background, self.na,
            self.pixel_size_um, self.n_slices, self.slice_spacing_um, self.image_plane_um, self.apply_button,
            Label(value="<b>Sources</b>"), self.depth_um, self.fit_button, self.file_sources_button,
            Label(value="<b>Previews</b>"), self.mask_threshold, self.masks_button, self.image_index,
            self.preview_button, self.feedback.label,
        ])
        self._set_optics_fields(DEFAULT_OPTICS)
        self.tasks = BackgroundTasks(napari_viewer, self.feedback, self.native)
        self._shown = None
        self.layer.changed.connect(self._on_layer_changed)
        self.apply_button.changed.connect(self.apply_optics)
        self.fit_button.changed.connect(self.fit_sources)
        self.file_sources_button.changed.connect(self.sources_from_file)
        self.masks_button.changed.connect(self.preview_masks)
        self.preview_button.changed.connect(self.preview_image)
        follow_layers(napari_viewer, self.layer, self._refresh)

    # -- layer selection ----------------------------------------------------------------------
    def _choices(self, _widget=None) -> list[tuple[str, object]]:
        return acquisition_layer_choices(self._viewer)

    def _refresh(self, _event=None) -> None:
        refresh_layer_choice(self.layer)
        if self.layer.value is not self._shown:
            self._on_layer_changed(self.layer.value)

    def _set_optics_fields(self, values: dict) -> None:
        for name in OPTICS_FIELDS:
            getattr(self, name).value = values[name]

    def _on_layer_changed(self, layer=None) -> None:
        self._shown = layer
        if layer is None:
            return
        acq = layer.metadata.get(META_ACQUISITION)
        if acq is not None:
            self._set_optics_fields(acq.optics.to_dict())
            if acq.sources_um is not None:
                self.depth_um.value = float(np.median(acq.sources_um[:, 2]))
            self.feedback.info(f"{layer.name}: {acq.n_images} images of {acq.image_shape[0]}×{acq.image_shape[1]} px")
        elif layer.metadata.get(META_NEEDS_OPTICS):
            self.feedback.info(f"{layer.name} has no optics: enter them and press Apply optics")
        self.image_index.max = max(0, int(np.shape(layer.data)[0]) - 1)

    # -- actions ------------------------------------------------------------------------------
    def optics(self) -> Optics:
        """The optics in the fields, checked by the core (raises :class:`FDTInputError`)."""
        return Optics(**{name: getattr(self, name).value for name in OPTICS_FIELDS})

    def current_acquisition(self) -> tuple[object, Acquisition]:
        """(layer, acquisition) with the optics of the fields applied to the layer (metadata, scale)."""
        layer = self.layer.value
        if layer is None:
            raise no_layer()
        optics = self.optics()
        acq = layer.metadata.get(META_ACQUISITION)
        if acq is None or acq.optics != optics:
            if acq is None:
                acq = Acquisition(images=np.asarray(layer.data), optics=optics)
            else:
                acq = Acquisition(images=acq.images, optics=optics, sources_um=acq.sources_um, extra=acq.extra)
            layer.metadata[META_ACQUISITION] = acq
            layer.metadata.pop(META_NEEDS_OPTICS, None)
            layer.metadata[META_KIND] = "acquisition"
            layer.scale = stack_scale(optics.pixel_size_um)
            layer.translate = stack_translate(acq.image_shape, optics.pixel_size_um)
        return layer, acq

    def apply_optics(self) -> None:
        """Check the optics and store them on the layer."""
        with self.feedback.guard():
            layer, acq = self.current_acquisition()
            o = acq.optics
            self.feedback.info(f"optics applied to {layer.name}: volume {o.n_slices} × {o.slice_spacing_um:g} µm, "
                               f"pixel {o.pixel_size_um:g} µm")

    def fit_sources(self):
        """2-D Gaussian fit of every image (in a worker thread) → the sources points layer."""
        from napari_fdt.recon.source_fit import initial_sources

        job = None
        with self.feedback.guard():
            layer, acq = self.current_acquisition()
            depth = self.depth_um.value or None
            job = lambda: initial_sources(acq, depth_um=depth, device="cpu")  # noqa: E731

        def show(result) -> None:
            sources, report = result
            self._check_still_open(layer)
            set_sources(self._viewer, layer, sources)
            reliable = int(np.sum(report["lateral_reliable"]))
            self.feedback.info(f"fitted {len(sources)} sources ({reliable} reliable), depth "
                               f"{np.median(sources[:, 2]):.1f} µm ({report['depth_source']}); edit the points to correct them")

        if job is None:
            return None
        return self.tasks.start("fit sources", job, show, buttons=(self.fit_button,),
                                message=f"fitting the sources of {layer.name}…")

    def _check_still_open(self, layer) -> None:
        if layer not in self._viewer.layers:
            from napari_fdt.errors import FDTInputError

            raise FDTInputError("layer", f"{layer.name} was closed while the result was computed", "open it again")

    def sources_from_file(self) -> None:
        """The acquisition's own ``sources_um`` → the sources points layer."""
        with self.feedback.guard():
            layer, acq = self.current_acquisition()
            if acq.sources_um is None:
                from napari_fdt.errors import FDTInputError

                raise FDTInputError("sources_um", f"{layer.name} has none", "press Fit sources")
            set_sources(self._viewer, layer, acq.sources_um)
            self.feedback.info(f"{len(acq.sources_um)} sources from the file")

    def preview_masks(self):
        """The coherence masks of all sources (in a worker thread) → an image stack layer."""
        job = None
        with self.feedback.guard():
            layer, acq = self.current_acquisition()
            sources = sources_for(self._viewer, layer, acq)
            threshold = float(self.mask_threshold.value)
            job = lambda: mask_stack(acq, sources, threshold=threshold)  # noqa: E731

        def show(masks: np.ndarray) -> None:
            self._check_still_open(layer)
            o = acq.optics
            put_layer(self._viewer, (masks, dict(
                name=f"{layer.name} masks", scale=stack_scale(o.pixel_size_um),
                translate=stack_translate(acq.image_shape, o.pixel_size_um), units=UNITS, colormap="green",
                blending="additive", opacity=0.5, contrast_limits=(0, 1),
                metadata={META_KIND: "masks", META_OWNER: layer.metadata[META_ID]}), "image"))
            self.feedback.info(f"masks of {len(masks)} sources: {100 * masks.mean():.0f} % of the pixels on average")

        if job is None:
            return None
        return self.tasks.start("preview masks", job, show, buttons=(self.masks_button,),
                                message=f"computing the masks of {layer.name}…")

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
            put_layer(self._viewer, (side_by_side(pred, meas), dict(
                name=f"{layer.name} preview: model | measured", scale=(dx, dx),
                translate=lateral_translate(acq.image_shape, dx), units=UNITS[:2], colormap="gray",
                metadata={META_KIND: "preview", META_OWNER: layer.metadata[META_ID], "fdt_image": index}), "image"))
            rel = float(np.linalg.norm(pred - meas) / max(float(np.linalg.norm(meas)), 1e-30))
            self.feedback.info(f"image {index} ({medium}): relative difference {rel:.3f} after a least-squares gain")

        if job is None:
            return None
        return self.tasks.start("forward preview", job, show, buttons=(self.preview_button,),
                                message=f"predicting image {index} of {layer.name}…")
