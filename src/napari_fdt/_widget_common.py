"""What both widgets share (imports napari): finding the plugin's layers, adding or updating them, and
showing the core's messages in the widget and as napari notifications.

Layers find each other through their metadata (``napari_fdt._layers``): an acquisition layer has an
``fdt_id``; the sources, RI, masks, coverage and comparison layers derived from it carry that id as
``fdt_owner`` and their ``fdt_kind``. Layer names are for people and may be changed freely.
"""

from __future__ import annotations

import contextlib
import warnings
from typing import Iterator

import numpy as np
from magicgui.widgets import Label
from napari.layers import Image, Layer, Points
from napari.utils.notifications import show_error, show_warning

from ._layers import (
    META_ACQUISITION, META_ID, META_KIND, META_NEEDS_OPTICS, META_OWNER, LayerDataTuple, points_to_sources,
    sources_layer,
)
from .acquisition import Acquisition
from .errors import FDTInputError, FDTWarning

__all__ = [
    "acquisition_layer_choices", "find_layer", "put_layer", "sources_for", "set_sources", "Feedback",
    "acquisition_of", "no_layer",
]

def no_layer() -> FDTInputError:
    """The error for actions that need an acquisition layer when none is open."""
    return FDTInputError(
        "layer", "no acquisition or image stack is open",
        "open an acquisition folder or a TIFF stack (File > Open), or a sample (File > Open Sample > napari-fdt)",
    )


def acquisition_layer_choices(viewer) -> list[tuple[str, Image]]:
    """(name, layer) of every image layer that is an acquisition or a bare stack waiting for optics."""
    return [(layer.name, layer) for layer in viewer.layers
            if isinstance(layer, Image) and (META_ACQUISITION in layer.metadata or layer.metadata.get(META_NEEDS_OPTICS))]


def follow_layers(viewer, combo, refresh) -> None:
    """Keep a layer combo box in step with the viewer: ``refresh`` runs now and whenever layers come or go."""
    events = viewer.layers.events
    events.inserted.connect(refresh)
    events.removed.connect(refresh)
    refresh()


def refresh_layer_choice(combo) -> None:
    """Re-read the combo's choices and select the first one when nothing is selected."""
    combo.reset_choices()
    if combo.value is None and combo.choices:
        combo.value = combo.choices[0]


def acquisition_of(layer: Image | None) -> Acquisition:
    """The layer's acquisition; :class:`FDTInputError` when there is no layer or its optics are not set."""
    if layer is None:
        raise no_layer()
    acq = layer.metadata.get(META_ACQUISITION)
    if acq is None:
        raise FDTInputError("optics", f"{layer.name} has no optics yet",
                            "enter them in the FDT acquisition widget and press Apply optics")
    return acq


def find_layer(viewer, owner: str | None, kind: str, layer_type: type[Layer] = Layer) -> Layer | None:
    """The most recent layer of ``kind`` belonging to acquisition ``owner`` (None if none)."""
    found = [layer for layer in viewer.layers if isinstance(layer, layer_type)
             and layer.metadata.get(META_KIND) == kind and layer.metadata.get(META_OWNER) == owner]
    return found[-1] if found else None


def put_layer(viewer, layer_data: LayerDataTuple) -> Layer:
    """Update the layer of the same kind and owner in place (data, scale, placement, metadata), or add it."""
    data, kwargs, layer_type = layer_data
    meta = kwargs.get("metadata", {})
    cls = {"image": Image, "points": Points}[layer_type]
    layer = find_layer(viewer, meta.get(META_OWNER), meta.get(META_KIND), cls)
    if layer is None or (layer_type == "image" and np.ndim(layer.data) != np.ndim(data)):
        if layer is not None:
            viewer.layers.remove(layer)
        return getattr(viewer, f"add_{layer_type}")(data, **kwargs)
    layer.data = data
    for key in ("scale", "translate"):
        if key in kwargs:
            setattr(layer, key, kwargs[key])
    layer.metadata.update(meta)
    if layer_type == "image":
        layer.reset_contrast_limits()
    return layer


def sources_for(viewer, layer: Image, acq: Acquisition, required: bool = True) -> np.ndarray | None:
    """Source positions (N, 3) µm for an acquisition: the (edited) points layer, else the file's, else None/error."""
    points = find_layer(viewer, layer.metadata.get(META_ID), "sources", Points)
    if points is not None:
        return points_to_sources(points.data, acq.n_images)
    if acq.sources_um is not None:
        return acq.sources_um
    if required:
        raise FDTInputError("sources", f"{layer.name} has no source positions",
                            "press Fit sources in the FDT acquisition widget")
    return None


def set_sources(viewer, layer: Image, sources_um: np.ndarray) -> Points:
    """Show ``sources_um`` (N, 3) in the acquisition's points layer (updated in place, or added)."""
    return put_layer(viewer, sources_layer(sources_um, f"{layer.name} sources", layer.metadata.get(META_ID)))


class Feedback:
    """A label in the widget for messages, mirrored as napari notifications.

    ``with feedback.guard():`` turns :class:`FDTInputError` into an error message and :class:`FDTWarning` into warnings, so the widget stays usable.
    """

    def __init__(self) -> None:
        self.label = Label(value="")
        self.label.native.setWordWrap(True)
        self.last_error: str | None = None

    def error(self, message: str) -> None:
        self.last_error = message
        self.label.value = f"error: {message}"
        self.label.native.setStyleSheet("color: #ff6060;")
        show_error(message)

    def info(self, message: str) -> None:
        self.last_error = None
        self.label.value = message
        self.label.native.setStyleSheet("")

    def warn(self, message: str) -> None:
        self.label.value = f"warning: {message}"
        self.label.native.setStyleSheet("color: #ffb040;")
        show_warning(message)

    @contextlib.contextmanager
    def guard(self) -> Iterator[None]:
        """Run a user action: errors become one message, warnings are shown."""
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", FDTWarning)
            try:
                yield
            except FDTInputError as exc:
                self.error(str(exc))
                return
        for w in caught:
            if issubclass(w.category, FDTWarning):
                self.warn(str(w.message))
            else:
                warnings.showwarning(w.message, w.category, w.filename, w.lineno)
