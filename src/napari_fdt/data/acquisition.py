"""An acquisition: the stack of fluorescence images, the optics and the point-source positions.

This is the in-memory form of the acquisition folder, format version 1 (see
``docs/format.md``): ``images.tif`` holding ``N`` images of ``H x W`` pixels, and
``acquisition.json`` holding the optics (:class:`~napari_fdt.physics.optics.Optics`), optionally one
source position per image (``sources_um``) and any further keys, which are kept unchanged in
:attr:`Acquisition.extra`.

All lengths are in micrometres.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from napari_fdt.data.mapped import MappedFile, chunks, mapped_file
from napari_fdt.errors import FDTInputError, FDTWarning
from napari_fdt.physics.optics import OPTICS_FIELDS, Optics

__all__ = [
    "Acquisition",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "RESERVED_KEYS",
    "check_image_layout",
    "check_sources",
    "parse_metadata",
]

#: Value of the ``format`` key of ``acquisition.json``.
FORMAT_NAME = "fdt-acquisition"
#: The format version this module reads and writes.
FORMAT_VERSION = 1
#: Keys of ``acquisition.json`` with a meaning; every other key goes to ``Acquisition.extra``.
RESERVED_KEYS = frozenset(("format", "version", "images", "sources_um", *OPTICS_FIELDS))

#: Smallest accepted image height and width, pixels.
MIN_IMAGE_SIDE = 8

# Accepted pixel types and the type they are stored as.
_DTYPE_STORED = {
    np.dtype(np.float32): np.dtype(np.float32),
    np.dtype(np.float64): np.dtype(np.float32),
    np.dtype(np.uint8): np.dtype(np.uint16),
    np.dtype(np.uint16): np.dtype(np.uint16),
}
_DTYPE_FIX = "save the images as float32 or uint16 grayscale (uint8 and float64 are converted)"


def _stored_dtype(dtype: Any) -> np.dtype | None:
    """The type pixels of ``dtype`` are stored as, or None if unsupported (byte order ignored)."""
    try:
        dt = np.dtype(dtype)
    except TypeError:
        return None
    if dt.kind not in "fu":
        return None
    return _DTYPE_STORED.get(dt.newbyteorder("="))


def check_image_layout(shape: Sequence[int], dtype: Any, field_name: str = "images") -> tuple[int, int, int]:
    """Check the shape and pixel type of an image stack without looking at its pixels.

    Parameters
    ----------
    shape:
        ``(H, W)`` for a single image or ``(N, H, W)`` for a stack.
    dtype:
        Pixel type; float32, float64, uint8 or uint16.
    field_name:
        Field named in the error.

    Returns
    -------
    ``(N, H, W)``.

    Raises
    ------
    FDTInputError
        For another number of dimensions, an empty stack, images smaller than 8 x 8 pixels or
        an unsupported pixel type.
    """
    shape = tuple(int(s) for s in shape)
    if len(shape) == 2:
        shape = (1, *shape)
    if len(shape) != 3:
        raise FDTInputError(
            field_name,
            f"must be one image (H, W) or a stack (N, H, W), got {len(shape)}-D shape {shape}",
            "save one grayscale image per source, stacked along the first axis",
        )
    n, h, w = shape
    if n < 1:
        raise FDTInputError(field_name, "holds no images", "give at least one image")
    if h < MIN_IMAGE_SIDE or w < MIN_IMAGE_SIDE:
        raise FDTInputError(
            field_name,
            f"images of {h} x {w} pixels are too small (shape {shape})",
            f"images must be at least {MIN_IMAGE_SIDE} x {MIN_IMAGE_SIDE} pixels; "
            "check the axis order is (N, H, W)",
        )
    if _stored_dtype(dtype) is None:
        raise FDTInputError(field_name, f"pixel type {dtype} is not supported", _DTYPE_FIX)
    return n, h, w


def _number(field_name: str, value: Any) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise FDTInputError(field_name, f"must be a number, got {value!r}", "write a plain number, µm")
    return float(value)


def _coerce_sources(sources: Any) -> np.ndarray:
    """``sources_um`` as a float64 array (copy), checking the entries are numbers; shape unchecked."""
    fix = "give one [x_um, y_um, depth_um] per image"
    if isinstance(sources, np.ndarray):
        if sources.dtype.kind not in "iuf":
            raise FDTInputError("sources_um", f"must hold real numbers, got dtype {sources.dtype}", fix)
        return np.array(sources, dtype=np.float64)
    if isinstance(sources, (str, bytes)) or not isinstance(sources, Sequence):
        raise FDTInputError("sources_um", f"must be a list of [x_um, y_um, depth_um], got {sources!r}", fix)
    rows = []
    for i, entry in enumerate(sources):
        name = f"sources_um[{i}]"
        if isinstance(entry, np.ndarray):
            entry = entry.tolist()
        if isinstance(entry, (str, bytes)) or not isinstance(entry, Sequence) or len(entry) != 3:
            raise FDTInputError(name, f"must be [x_um, y_um, depth_um], got {entry!r}", fix)
        rows.append([_number(name, v) for v in entry])
    return np.array(rows, dtype=np.float64).reshape(len(rows), 3)


def check_sources(sources: np.ndarray, n_images: int | None) -> None:
    """Check shape ``(N, 3)``, the count against ``n_images`` (if given), finiteness and depth > 0."""
    if sources.ndim != 2 or sources.shape[1] != 3:
        raise FDTInputError(
            "sources_um",
            f"must have shape (N, 3), one [x_um, y_um, depth_um] per image, got shape {sources.shape}",
            "give one [x_um, y_um, depth_um] per image",
        )
    if n_images is not None and sources.shape[0] != n_images:
        raise FDTInputError(
            "sources_um",
            f"holds {sources.shape[0]} source positions but there are {n_images} images",
            "give exactly one [x_um, y_um, depth_um] per image, in the order of the images",
        )
    finite = np.isfinite(sources).all(axis=1)
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        raise FDTInputError(
            f"sources_um[{i}]", f"must be finite, got {sources[i].tolist()}", "write finite numbers, µm"
        )
    shallow = sources[:, 2] <= 0
    if shallow.any():
        i = int(np.flatnonzero(shallow)[0])
        raise FDTInputError(
            f"sources_um[{i}]",
            f"depth {sources[i, 2]:g} µm is not positive",
            "depth is measured below the volume's bottom face and must be positive",
        )


def parse_metadata(
    metadata: Mapping[str, Any], n_images: int | None = None
) -> tuple[Optics, np.ndarray | None, dict[str, Any]]:
    """Check the metadata of ``acquisition.json`` without the pixels.

    Parameters
    ----------
    metadata:
        The parsed JSON object.
    n_images:
        Number of images, if already known, to check ``sources_um`` against.

    Returns
    -------
    ``(optics, sources_um, extra)``: the optics, the source positions as a float64 ``(N, 3)``
    array in µm or ``None``, and a copy of the keys this format version does not define.

    Raises
    ------
    FDTInputError
        Naming the first offending key.
    """
    if not isinstance(metadata, Mapping):
        raise FDTInputError(
            "acquisition.json", f"top level must be a JSON object, got {type(metadata).__name__}",
            'write an object: {"format": "fdt-acquisition", "version": 1, ...}',
        )
    if "format" not in metadata:
        raise FDTInputError("format", "is missing", f'add "format": "{FORMAT_NAME}"')
    if metadata["format"] != FORMAT_NAME:
        raise FDTInputError(
            "format", f"must be {FORMAT_NAME!r}, got {metadata['format']!r}",
            "this is not a napari-fdt acquisition; check the folder",
        )
    if "version" not in metadata:
        raise FDTInputError("version", "is missing", f'add "version": {FORMAT_VERSION}')
    version = metadata["version"]
    if isinstance(version, bool) or not isinstance(version, (int, np.integer)):
        raise FDTInputError("version", f"must be a whole number, got {version!r}", f'write "version": {FORMAT_VERSION}')
    if version > FORMAT_VERSION:
        raise FDTInputError(
            "version", f"{version} was written by a newer napari-fdt (this one reads version {FORMAT_VERSION})",
            "upgrade napari-fdt",
        )
    if version != FORMAT_VERSION:
        raise FDTInputError("version", f"{version} is not a known version", f'write "version": {FORMAT_VERSION}')
    optics = Optics.from_mapping(metadata)
    sources = metadata.get("sources_um")
    if sources is not None:
        sources = _coerce_sources(sources)
        check_sources(sources, n_images)
    extra = {k: v for k, v in metadata.items() if k not in RESERVED_KEYS}
    return optics, sources, extra


def _checked_float(images: np.ndarray) -> np.ndarray:
    """Float images (N, H, W) checked for NaN/Inf, as float32, warning about negative pixels; chunk by chunk, so a
    memory-mapped stack is read once without a temporary of its size (a float64 stack is converted: a copy)."""
    stored = _stored_dtype(images.dtype)
    out = images if images.dtype == stored else np.empty(images.shape, dtype=stored)
    negative = 0
    for s in chunks(images):
        part = images[s]
        finite = np.isfinite(part)
        if not finite.all():
            bad = sum(int((~np.isfinite(images[t])).sum()) for t in chunks(images) if t.start >= s.start)
            first = np.unravel_index(int(np.argmax(~finite)), part.shape)
            raise FDTInputError(
                "images",
                f"{bad} non-finite pixels (NaN or Inf), first at image {s.start + int(first[0])}, "
                f"row {first[1]}, col {first[2]}",
                "replace or mask the bad pixels before reconstruction",
            )
        if out is not images:
            converted = part.astype(stored)
            if not np.isfinite(converted).all():
                raise FDTInputError("images", "pixel values exceed the float32 range", "rescale the images")
            out[s] = converted
        negative += int((part < 0).sum())
    if negative:
        warnings.warn(
            f"images: {negative} negative pixels; fluorescence intensities should be >= 0 "
            "(background subtraction may have overshot)",
            FDTWarning,
            stacklevel=4,
        )
    return out


@dataclass(eq=False)
class Acquisition:
    """A stack of images with the optics and, optionally, one point-source position per image.

    Attributes
    ----------
    images:
        ``(N, H, W)`` pixel values, float32 or uint16 (float64 is converted to float32, uint8 to
        uint16, a single ``(H, W)`` image becomes ``(1, H, W)``). H and W at least 8.
    optics:
        Optics and sampling.
    sources_um:
        ``(N, 3)`` float64: ``[x_um, y_um, depth_um]`` of each image's source, x and y from the
        image centre, depth below the volume's bottom face (> 0); or ``None`` if unknown.
    extra:
        Keys of ``acquisition.json`` this format version does not define, written back unchanged.
    """

    images: np.ndarray
    optics: Optics
    sources_um: np.ndarray | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        images = self.images
        if not isinstance(images, np.ndarray):
            raise FDTInputError(
                "images", f"must be a numpy array, got {type(images).__name__}", "pass numpy.asarray(images)"
            )
        n, h, w = check_image_layout(images.shape, images.dtype)
        images = images.reshape(n, h, w)
        if images.dtype.kind == "f":
            images = _checked_float(images)
        else:
            images = images.astype(_stored_dtype(images.dtype), copy=False)
        self.images = images

        if not isinstance(self.optics, Optics):
            raise FDTInputError(
                "optics", f"must be an Optics, got {type(self.optics).__name__}", "build it with Optics(...)"
            )
        if self.sources_um is not None:
            sources = _coerce_sources(self.sources_um)
            check_sources(sources, n)
            self.sources_um = sources
        if not isinstance(self.extra, Mapping):
            raise FDTInputError("extra", f"must be a dict, got {type(self.extra).__name__}", "pass a dict")
        clash = sorted(k for k in self.extra if k in RESERVED_KEYS)
        if clash:
            raise FDTInputError(
                "extra", f"holds keys the format defines: {', '.join(map(str, clash))}",
                "set those through images, optics and sources_um",
            )
        bad_keys = [k for k in self.extra if not isinstance(k, str)]
        if bad_keys:
            raise FDTInputError("extra", f"keys must be strings, got {bad_keys[0]!r}", "use string keys")
        self.extra = dict(self.extra)

    @property
    def n_images(self) -> int:
        """Number of images N."""
        return int(self.images.shape[0])

    @property
    def image_shape(self) -> tuple[int, int]:
        """``(H, W)`` of each image, pixels."""
        return int(self.images.shape[1]), int(self.images.shape[2])

    def __getstate__(self) -> dict[str, Any]:
        """Pickled with a memory-mapped stack as its file reference: another process maps the file, not a copy."""
        state = dict(self.__dict__)
        ref = mapped_file(self.images)
        if ref is not None:
            state["images"] = ref
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        if isinstance(state.get("images"), MappedFile):
            state = {**state, "images": state["images"].open()}
        self.__dict__.update(state)

    def images_float32(self) -> np.ndarray:
        """The ``(N, H, W)`` images as float32: the stored array itself if already float32, else a copy."""
        return self.images.astype(np.float32, copy=False)

    @classmethod
    def from_metadata(cls, images: np.ndarray, metadata: Mapping[str, Any]) -> "Acquisition":
        """Build from the pixels and the parsed ``acquisition.json`` object (checked first)."""
        n_images = None
        if isinstance(images, np.ndarray) and images.ndim in (2, 3):
            n_images = 1 if images.ndim == 2 else int(images.shape[0])
        optics, sources, extra = parse_metadata(metadata, n_images)
        return cls(images=images, optics=optics, sources_um=sources, extra=extra)

    def to_metadata(self, images_name: str = "images.tif") -> dict[str, Any]:
        """The ``acquisition.json`` object: format keys, optics, ``sources_um`` (omitted if None), extra keys."""
        meta: dict[str, Any] = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "images": images_name}
        meta.update(self.optics.to_dict())
        if self.sources_um is not None:
            meta["sources_um"] = [[float(v) for v in row] for row in self.sources_um]
        for key, value in self.extra.items():
            if key not in RESERVED_KEYS:
                meta[key] = value
        return meta
