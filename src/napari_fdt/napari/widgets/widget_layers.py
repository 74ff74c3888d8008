"""The plugin's layers as the widgets see them (imports napari): which layers hold an acquisition, adding or updating
the layers derived from one, and the sources of a stack.

Layers find each other through their metadata (``napari_fdt.napari.layers``): an acquisition layer has an
``fdt_id``; the sources, RI, masks, coverage and comparison layers derived from it carry that id as
``fdt_owner`` and their ``fdt_kind``. Layer names are for people and may be changed freely.
"""


import numpy as np
from napari.layers import Image, Layer, Points

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.errors import FDTInputError
from napari_fdt.napari.layers import (
    META_ACQUISITION,
    META_ID,
    META_KIND,
    META_NEEDS_OPTICS,
    META_OWNER,
    META_PATH,
    LayerDataTuple,
    acquisition_layer,
    new_id,
    points_to_sources,
    source_point_size_um,
    sources_layer,
)

__all__ = [
    "acquisition_layer_choices", "find_layer", "put_layer", "sources_for", "set_sources", "acquisition_of", "no_layer",
    "adopt_layer", "follow_layers", "refresh_layer_choice", "is_image_stack", "DERIVED_KINDS",
]


def no_layer() -> FDTInputError:
    """The error for actions that need an acquisition layer when none is open."""
    return FDTInputError(
        "images", "no image stack is open",
        "open an acquisition folder (File > Open Folder…, reader napari-fdt) or a TIFF stack (File > Open File(s)…), "
        "or a sample (File > Open Sample > napari-fdt)",
    )


#: Layer kinds the plugin derives from an acquisition: never offered as the images of a reconstruction.
DERIVED_KINDS = frozenset({"ri", "truth", "masks", "preview", "coverage", "comparison"})


def is_image_stack(layer) -> bool:
    """An image layer that can hold a stack of camera images (N, H, W) or (N, 1, H, W), whichever reader opened it."""
    if not isinstance(layer, Image) or getattr(layer, "rgb", False) or layer.metadata.get(META_KIND) in DERIVED_KINDS:
        return False
    shape = tuple(np.shape(layer.data))
    return len(shape) == 3 or (len(shape) == 4 and shape[1] == 1)


def acquisition_layer_choices(viewer) -> list[tuple[str, Image]]:
    """(name, layer) of every image layer that may be a stack: the plugin's own, and those of any other reader."""
    return [(layer.name, layer) for layer in viewer.layers if is_image_stack(layer)]


def adopt_layer(viewer, layer: Image, acq: Acquisition) -> Image:
    """Make ``layer`` the acquisition ``acq`` (metadata, physical scale, the image index on its own axis).

    A stack from another reader is (N, H, W): it is replaced, at the same place in the layer list and with the
    same name, by the plugin's (N, 1, H, W) layer (the data are shared, not copied). Returns the layer now shown.
    """
    data, kwargs, _ = acquisition_layer(acq, path=layer.metadata.get(META_PATH), name=layer.name)
    meta = dict(layer.metadata)
    meta.update(kwargs.pop("metadata"))
    meta[META_ID] = layer.metadata.get(META_ID) or new_id()
    meta.pop(META_NEEDS_OPTICS, None)
    if np.ndim(layer.data) == 4:
        layer.metadata.update(meta)
        layer.metadata.pop(META_NEEDS_OPTICS, None)
        layer.units = kwargs["units"]
        layer.scale = kwargs["scale"]
        layer.translate = kwargs["translate"]
        return layer
    index = list(viewer.layers).index(layer)
    kwargs.update(metadata=meta, contrast_limits=layer.contrast_limits, visible=layer.visible)
    new = viewer.add_image(data, **kwargs)
    viewer.layers.remove(layer)
    viewer.layers.move(list(viewer.layers).index(new), index)
    new.name = layer.name
    return new


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
        from napari_fdt.napari.layers import META_FILE_OPTICS, META_OPTICS_ENTRIES
        from napari_fdt.napari.settings import format_entry, missing_optics

        entries = {k: format_entry(v) for k, v in (layer.metadata.get(META_FILE_OPTICS) or {}).items()}
        entries.update({k: v for k, v in (layer.metadata.get(META_OPTICS_ENTRIES) or {}).items() if v})
        missing = missing_optics(entries)
        raise FDTInputError("optics", f"{layer.name} has no optics yet" + (f" (missing {', '.join(missing)})" if missing else ""),
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


def set_sources(viewer, layer: Image, sources_um: np.ndarray, *, kind: str = "sources", name: str | None = None) -> Points:
    """Show ``sources_um`` (N, 3) in the acquisition's points layer of ``kind`` (updated in place, or added).

    ``kind`` ``sources``: the editable start of a run (Fit sources, Sources from file); ``calibrated``: a run's
    calibrated positions, in a layer of their own (``name``), so a calibration never overwrites the edited points.
    """
    acq = layer.metadata.get(META_ACQUISITION)
    size = source_point_size_um(acq.image_shape, acq.optics.pixel_size_um) if acq is not None else 1.0
    colour = "cyan" if kind == "sources" else "orange"
    data = sources_layer(sources_um, name or f"{layer.name} sources", layer.metadata.get(META_ID), size_um=size,
                         kind=kind, colour=colour)
    if kind != "sources" and name is not None:  # one layer per run, found by name
        for old in viewer.layers:
            if isinstance(old, Points) and old.name == name and old.metadata.get(META_KIND) == kind:
                old.data = data[0]
                return old
        return viewer.add_points(data[0], **data[1])
    return put_layer(viewer, data)


