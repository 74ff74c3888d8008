"""Microscope files in: TIFF stacks (OME-TIFF, ImageJ, plain) and per-source image files, with the optics they record.

An FDT acquisition is N images, one per excited source. Microscopes write them as one multi-image TIFF
(the image index along T, Z, C or pages) or as one 2-D file per source. This module reads both through
tifffile's own metadata parsing and returns the images with the :class:`~napari_fdt.physics.optics.Optics`
fields the file states, in µm:

========================  ==================================================================================
field                     where it comes from
========================  ==================================================================================
``pixel_size_um``         OME ``Pixels/@PhysicalSizeX`` (and Y, equal); ImageJ ``XResolution`` with its
                          ``unit``; a plain TIFF's ``XResolution`` with ``ResolutionUnit`` centimetre
``wavelength_um``         OME ``Channel/@EmissionWavelength`` (the detected fluorescence; all channels of
                          the stack agreeing)
``na``                    OME ``Objective/@LensNA`` of the image's ``ObjectiveSettings`` (or the only
                          objective of the file)
``n_background``          OME ``ObjectiveSettings/@RefractiveIndex`` (the immersion medium's index)
========================  ==================================================================================

A field the file does not state is absent from the dict (never a default): the caller asks the user.
The volume's sampling (``n_slices``, ``slice_spacing_um``) is never in a microscope file; a z step of the
stack is the focus step of a z-stack, not the RI grid, and is not used.

:func:`probe_stack` decides from the header alone (no pixels read) whether a file is a stack this package
reads; :func:`read_stack` and :func:`read_source_files` then read the pixels. No napari, no torch.

Other microscope formats (Nikon ``.nd2``, Zeiss ``.czi``, Leica ``.lif``) are read through bioio and its reader
plugins where the optional ``formats`` extra is installed (``pip install "napari-fdt[formats]"``): the pixels
through ``BioImage``, the optics from the OME metadata bioio converts the file's own to (the same table,
:func:`ome_optics`), else the pixel size from ``physical_pixel_sizes``. TIFFs stay with tifffile: bioio 3.6 reports
an OME ``PhysicalSizeX="325" PhysicalSizeXUnit="nm"`` as 325 (µm), where tifffile's XML gives the unit.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import tifffile

from napari_fdt.data.acquisition import check_image_layout
from napari_fdt.data.io import _OME_UNITS_UM, _quiet_tifffile, check_fits_in_memory
from napari_fdt.data.mapped import map_series
from napari_fdt.errors import FDTInputError

__all__ = ["StackHeader", "FileStack", "TIFF_SUFFIXES", "BIOIO_SUFFIXES", "has_bioio", "probe_stack", "read_stack", "read_source_files",
           "list_source_files", "natural_key"]

#: File name endings read as TIFF.
TIFF_SUFFIXES = (".tif", ".tiff")
#: File name endings read through bioio (the ``formats`` extra), when it is installed.
BIOIO_SUFFIXES = (".nd2", ".czi", ".lif")

# ImageJ writes its unit as text: "micron", "um", "\u00B5m" (escaped), "nm", ...
_IMAGEJ_UNITS_UM = {**_OME_UNITS_UM, "\\u00b5m": 1.0, "\\u00B5m": 1.0, "mum": 1.0}
# TIFF ResolutionUnit: 3 centimetre (2 inch is left alone: it is a printing resolution, 72 dpi by default)
_RESUNIT_CM = 3
# wavelengths OME writes (EmissionWavelengthUnit), µm; OME's default is nm
_OME_WAVELENGTH_DEFAULT = "nm"


@dataclass(frozen=True)
class StackHeader:
    """What a file's header says: image count and size, pixel type, the optics found, the file kind.

    ``shape`` is ``(N, H, W)``; ``optics`` holds only the fields the file states (µm, NA, index);
    ``kind`` is ``"ome-tiff"``, ``"imagej-tiff"`` or ``"tiff"``; ``axes`` the series' axes as tifffile names them.
    """

    path: str
    shape: tuple[int, int, int]
    dtype: np.dtype
    optics: dict[str, float]
    kind: str
    axes: str
    is_ri_like: bool = False  # a float OME-TIFF volume (axes ZYX with a z voxel size), e.g. a napari-fdt RI volume


@dataclass
class FileStack:
    """Images read from microscope files, with the optics fields they state.

    ``images`` is ``(N, H, W)`` in the file's pixel type (uint8/uint16/float32/float64); ``optics`` the
    fields found (absent ones not present); ``paths`` the file(s) read, in image order; ``kind`` as in
    :class:`StackHeader`.
    """

    images: np.ndarray
    optics: dict[str, float]
    paths: list[str]
    kind: str
    notes: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------- metadata parsing


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _positive(value: Any, scale: float | None) -> float | None:
    try:
        v = float(value) * float(scale)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) and v > 0 else None


def ome_optics(ome_xml: str | None, series_index: int = 0) -> dict[str, float]:
    """Optics fields of image ``series_index`` of an OME-XML document (see the module's table)."""
    found: dict[str, float] = {}
    if not ome_xml:
        return found
    try:
        root = ET.fromstring(ome_xml)
    except ET.ParseError:
        return found
    images = [el for el in root if _local(el.tag) == "Image"]
    if not images:
        return found
    image = images[min(series_index, len(images) - 1)]
    pixels = next((el for el in image if _local(el.tag) == "Pixels"), None)
    if pixels is not None:
        sizes = []
        for axis in "XY":
            unit = pixels.get(f"PhysicalSize{axis}Unit", "µm")
            sizes.append(_positive(pixels.get(f"PhysicalSize{axis}"), _OME_UNITS_UM.get(unit)))
        dx, dy = sizes
        if dx is not None and (dy is None or abs(dx - dy) <= 1e-6 * dx):
            found["pixel_size_um"] = dx
        waves = []
        for ch in (el for el in pixels if _local(el.tag) == "Channel"):
            unit = ch.get("EmissionWavelengthUnit", _OME_WAVELENGTH_DEFAULT)
            waves.append(_positive(ch.get("EmissionWavelength"), _OME_UNITS_UM.get(unit)))
        if waves and all(w is not None for w in waves) and max(waves) - min(waves) <= 1e-6 * max(waves):
            found["wavelength_um"] = float(waves[0])
    settings = next((el for el in image if _local(el.tag) == "ObjectiveSettings"), None)
    objectives = [el for el in root.iter() if _local(el.tag) == "Objective"]
    objective = None
    if settings is not None:
        index = _positive(settings.get("RefractiveIndex"), 1.0)
        if index is not None and index >= 1:
            found["n_background"] = index
        objective = next((o for o in objectives if o.get("ID") == settings.get("ID")), None)
    if objective is None and len(objectives) == 1:
        objective = objectives[0]
    if objective is not None:
        na = _positive(objective.get("LensNA"), 1.0)
        if na is not None:
            found["na"] = na
    return found


def _resolution_um(page: tifffile.TiffPage, unit_um: float | None) -> float | None:
    """Pixel size from ``XResolution`` (pixels per unit) and ``YResolution``, µm; None if absent or unequal."""
    if unit_um is None:
        return None
    sizes = []
    for name in ("XResolution", "YResolution"):
        tag = page.tags.get(name)
        if tag is None:
            return None
        num, den = tag.value if isinstance(tag.value, tuple) else (tag.value, 1)
        if not num or not den:
            return None
        sizes.append(unit_um * den / num)
    dx, dy = sizes
    if not (math.isfinite(dx) and dx > 0) or abs(dx - dy) > 1e-6 * dx:
        return None
    return float(dx)


def imagej_optics(tif: tifffile.TiffFile) -> dict[str, float]:
    """``pixel_size_um`` of an ImageJ hyperstack: ``XResolution`` in the ``unit`` of its description."""
    meta = tif.imagej_metadata or {}
    unit = str(meta.get("unit", "")).strip()
    scale = _IMAGEJ_UNITS_UM.get(unit, _IMAGEJ_UNITS_UM.get(unit.lower()))
    size = _resolution_um(tif.pages.first, scale)
    return {} if size is None else {"pixel_size_um": size}


def tiff_optics(tif: tifffile.TiffFile) -> dict[str, float]:
    """``pixel_size_um`` of a plain TIFF whose ``ResolutionUnit`` is the centimetre."""
    page = tif.pages.first
    unit = page.tags.get("ResolutionUnit")
    if unit is None or int(unit.value) != _RESUNIT_CM:
        return {}
    size = _resolution_um(page, 1e4)
    return {} if size is None else {"pixel_size_um": size}


# --------------------------------------------------------------------------- header probe


def _stack_shape(series: Any) -> tuple[tuple[int, int, int], str] | None:
    """``(N, H, W)`` of a series with at most one axis besides Y and X longer than 1; None otherwise."""
    shape, axes = tuple(int(s) for s in series.shape), str(series.axes)
    if not axes.endswith("YX") or len(shape) != len(axes):
        return None
    h, w = shape[-2:]
    others = [s for s in shape[:-2] if s > 1]
    if len(others) > 1:
        return None
    return ((others[0] if others else 1), h, w), axes


def _header(tif: tifffile.TiffFile, path: str) -> StackHeader | None:
    if not tif.series:
        return None
    series = tif.series[0]
    layout = _stack_shape(series)
    if layout is None:
        return None
    shape, axes = layout
    try:
        check_image_layout(shape, series.dtype)
    except FDTInputError:
        return None
    if tif.is_ome:
        ome = tif.ome_metadata
        kind, optics = "ome-tiff", ome_optics(ome)
        ri_like = (np.dtype(series.dtype).kind == "f" and axes == "ZYX"
                   and "PhysicalSizeZ" in (ome or "") and "EmissionWavelength" not in (ome or "")
                   and "Objective" not in (ome or ""))
    elif tif.is_imagej:
        kind, optics, ri_like = "imagej-tiff", imagej_optics(tif), False
    else:
        kind, optics, ri_like = "tiff", tiff_optics(tif), False
    return StackHeader(path=path, shape=shape, dtype=np.dtype(series.dtype), optics=optics, kind=kind, axes=axes,
                       is_ri_like=ri_like)


def has_bioio() -> bool:
    """Whether bioio (the optional ``formats`` extra) is importable."""
    try:
        import bioio  # noqa: F401
    except ImportError:
        return False
    return True


def _bioio_image(path: Path):
    from bioio import BioImage

    with _quiet_tifffile():
        return BioImage(path)


def _bioio_header(img: Any, path: str) -> StackHeader | None:
    """The stack layout and optics of a ``BioImage`` (first scene), from its metadata; None if it is no stack."""
    dims = img.dims
    order = str(dims.order)
    shape = tuple(int(getattr(dims, a)) for a in order)
    if "S" in order and getattr(dims, "S") > 1:
        return None
    sizes = dict(zip(order, shape))
    others = [a for a in order if a not in "YXS" and sizes[a] > 1]
    if len(others) > 1:
        return None
    n = sizes[others[0]] if others else 1
    stack_shape = (n, sizes["Y"], sizes["X"])
    try:
        check_image_layout(stack_shape, img.dtype)
    except FDTInputError:
        return None
    optics: dict[str, float] = {}
    try:
        optics = ome_optics(img.ome_metadata.to_xml())
    except Exception:  # a reader without an OME conversion
        optics = {}
    if "pixel_size_um" not in optics:
        px = img.physical_pixel_sizes
        dx = _positive(px.X, 1.0)
        if dx is not None and (px.Y is None or abs(float(px.Y) - dx) <= 1e-6 * dx):
            optics["pixel_size_um"] = dx
    axes = (others[0] if others else "") + "YX"
    return StackHeader(path=path, shape=stack_shape, dtype=np.dtype(img.dtype), optics=optics, kind="bioio", axes=axes)


def _probe_bioio(p: Path) -> StackHeader | None:
    if not has_bioio():
        return None
    try:
        return _bioio_header(_bioio_image(p), str(p))
    except Exception:  # no plugin for the file, or a file it cannot parse: not ours to read
        return None


def probe_stack(path: str | Path) -> StackHeader | None:
    """The header of a file this package reads as an image stack, or None (not a TIFF (or, with bioio, an
    ND2/CZI/LIF file), unreadable, colour, several channels and times, images under 8×8 px or an unsupported
    pixel type). Reads no pixels."""
    p = Path(path)
    if p.suffix.lower() in BIOIO_SUFFIXES and p.is_file():
        return _probe_bioio(p)
    if p.suffix.lower() not in TIFF_SUFFIXES or not p.is_file():
        return None
    try:
        with _quiet_tifffile(), tifffile.TiffFile(p) as tif:
            return _header(tif, str(p))
    except Exception:  # tifffile raises many kinds on files it cannot parse: not ours to read
        return None


# --------------------------------------------------------------------------- reading


def _refuse_why(p: Path) -> FDTInputError:
    """The reason :func:`probe_stack` declined ``p``, as an error naming ``images``."""
    fix = "export one grayscale image per source, stacked along one axis (N, H, W), or one 2-D TIFF per source"
    if not p.is_file():
        return FDTInputError("images", f"{p} not found", "check the path")
    try:
        with _quiet_tifffile(), tifffile.TiffFile(p) as tif:
            if not tif.series:
                return FDTInputError("images", f"{p.name} holds no images", fix)
            series = tif.series[0]
            if _stack_shape(series) is None:
                return FDTInputError("images", f"{p.name} has axes {series.axes} and shape {series.shape}: more than one axis "
                                     "besides Y and X (e.g. channels and time), or colour samples", fix)
            check_image_layout(_stack_shape(series)[0], series.dtype)
    except FDTInputError as exc:
        return exc
    except Exception as exc:
        return FDTInputError("images", f"{p.name} is not a readable TIFF: {exc}", fix)
    return FDTInputError("images", f"{p.name} cannot be read as an image stack", fix)


def read_stack(path: str | Path) -> FileStack:
    """Read one TIFF as an ``(N, H, W)`` stack with the optics fields its metadata states.

    Raises :class:`FDTInputError` (field ``images``) for a file :func:`probe_stack` declines, or one too large
    for the memory (checked from the header).
    """
    p = Path(path)
    if p.suffix.lower() in BIOIO_SUFFIXES:
        return read_with_bioio(p)
    head = probe_stack(p)
    if head is None:
        raise _refuse_why(p)
    try:
        with _quiet_tifffile(), tifffile.TiffFile(p) as tif:
            mapped = map_series(p, tif.series[0])  # uncompressed and contiguous: read when used
            if mapped is None:
                check_fits_in_memory(p.name, head.shape, head.dtype)
            images = (tif.series[0].asarray() if mapped is None else mapped).reshape(head.shape)
    except MemoryError as exc:
        raise FDTInputError("images", f"{p.name}: not enough memory to read {head.shape} {head.dtype}",
                            "crop or bin the images") from exc
    except Exception as exc:  # a truncated file fails only when the pixels are read
        raise FDTInputError("images", f"{p.name} is not a readable TIFF: {exc}", "re-export it") from exc
    return FileStack(images=images, optics=dict(head.optics), paths=[str(p)], kind=head.kind)


def read_with_bioio(path: str | Path) -> FileStack:
    """Read a microscope file through bioio (first scene) as an ``(N, H, W)`` stack with the optics it states.

    Raises :class:`FDTInputError` (field ``images``) when bioio or a reader plugin for the file is missing, or the
    file is no single-channel stack.
    """
    p = Path(path)
    fix = 'install the readers: pip install "napari-fdt[formats]"'
    if not has_bioio():
        raise FDTInputError("images", f"{p.name} needs bioio to be read, which is not installed", fix)
    try:
        img = _bioio_image(p)
    except Exception as exc:
        raise FDTInputError("images", f"{p.name} cannot be read by bioio: {exc}", fix + ", or export the images as TIFF") from exc
    head = _bioio_header(img, str(p))
    if head is None:
        raise FDTInputError("images", f"{p.name} has dimensions {img.dims}: not one grayscale image per source along one axis",
                            "export one channel, one image per source (N, H, W)")
    check_fits_in_memory(p.name, head.shape, head.dtype)
    order = str(img.dims.order)
    keep = head.axes[0] if head.shape[0] > 1 and len(head.axes) == 3 else None
    squeeze = {a: 0 for a in order if a not in "YX" and a != keep}
    try:
        images = np.asarray(img.get_image_data((keep or "") + "YX", **squeeze))
    except Exception as exc:
        raise FDTInputError("images", f"{p.name}: bioio failed to read the pixels: {exc}", "export the images as TIFF") from exc
    return FileStack(images=images.reshape(head.shape), optics=dict(head.optics), paths=[str(p)], kind="bioio")


def natural_key(name: str) -> list[Any]:
    """Sort key putting ``img_2`` before ``img_10`` (runs of digits compared as numbers)."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_source_files(folder: str | Path) -> list[Path]:
    """The TIFF files of ``folder`` (not hidden), in natural order of their names: one image per source."""
    f = Path(folder)
    files = [p for p in f.iterdir() if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in TIFF_SUFFIXES]
    return sorted(files, key=lambda p: natural_key(p.name))


def probe_source_files(paths: Sequence[str | Path]) -> list[StackHeader] | None:
    """Headers of per-source files (each one 2-D image, all of one size and pixel type), or None."""
    heads = []
    for p in paths:
        head = probe_stack(p)
        if head is None or head.shape[0] != 1:
            return None
        heads.append(head)
    if not heads or len({(h.shape, h.dtype) for h in heads}) != 1:
        return None
    return heads


def read_source_files(paths: Sequence[str | Path] | str | Path) -> FileStack:
    """Read one 2-D TIFF per source (a list in image order, or a folder read in natural name order) as a stack.

    Every file must hold one image of the same size and pixel type. The optics are those the files state;
    a field stated differently by two files is dropped (with a note), since the stack has one value.
    """
    if isinstance(paths, (str, Path)):
        folder = Path(paths)
        if not folder.is_dir():
            raise FDTInputError("images", f"{folder} is not a folder", "give a folder of TIFFs or a list of files")
        files = list_source_files(folder)
        if not files:
            raise FDTInputError("images", f"{folder} holds no TIFF files", "put one .tif per source in the folder")
    else:
        files = [Path(p) for p in paths]
        if not files:
            raise FDTInputError("images", "no files given", "give one TIFF per source")
    heads = []
    for p in files:
        head = probe_stack(p)
        if head is None:
            raise _refuse_why(p)
        if head.shape[0] != 1:
            raise FDTInputError("images", f"{p.name} holds {head.shape[0]} images, not one",
                                "give one 2-D TIFF per source, or open the stack file itself")
        if heads and (head.shape, head.dtype) != (heads[0].shape, heads[0].dtype):
            raise FDTInputError("images", f"{p.name} is {head.shape[1]}x{head.shape[2]} {head.dtype}, "
                                f"{files[0].name} is {heads[0].shape[1]}x{heads[0].shape[2]} {heads[0].dtype}",
                                "give images of one size and pixel type")
        heads.append(head)
    n, (_, h, w) = len(heads), heads[0].shape
    check_fits_in_memory(files[0].name, (n, h, w), heads[0].dtype)
    images = np.empty((n, h, w), dtype=heads[0].dtype)
    for i, p in enumerate(files):
        try:
            with _quiet_tifffile(), tifffile.TiffFile(p) as tif:
                images[i] = tif.series[0].asarray().reshape(h, w)
        except Exception as exc:
            raise FDTInputError("images", f"{p.name} is not a readable TIFF: {exc}", "re-export it") from exc
    optics: dict[str, float] = {}
    notes = []
    for key in sorted({k for hd in heads for k in hd.optics}):
        values = [hd.optics.get(key) for hd in heads]
        if all(v is not None for v in values) and max(values) - min(values) <= 1e-6 * max(values):
            optics[key] = float(values[0])
        else:
            notes.append(f"{key} differs between the files (or is missing in some): left empty")
    kinds = {hd.kind for hd in heads}
    return FileStack(images=images, optics=optics, paths=[str(p) for p in files],
                     kind=kinds.pop() if len(kinds) == 1 else "tiff", notes=notes)
