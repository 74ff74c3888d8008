"""Reading and writing acquisition folders and volumes, never leaving a half-written file.

* :func:`read_acquisition` / :func:`write_acquisition`: the acquisition folder, format
  version 1 (``acquisition.json`` + ``images.tif``, see ``docs/format.md``).
* :func:`write_volume_tiff` / :func:`read_volume_tiff`: a 3-D float32 OME-TIFF (axes ZYX) with
  its voxel size in µm.
* :func:`write_json_atomic`: a JSON file.

Every writer builds its output under a temporary name next to the target (same folder, so the
same file system) and moves it into place with :func:`os.replace`; an interruption leaves
either the old output or the new one, plus at worst a hidden ``.NAME.tmp-*`` sibling. Readers
never modify their input and report every problem as :class:`~napari_fdt.errors.FDTInputError`
naming the offending field.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import secrets
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any, Iterator, Union

import numpy as np
import tifffile

from napari_fdt.data.acquisition import Acquisition, check_image_layout, check_sources, parse_metadata
from napari_fdt.data.mapped import map_series
from napari_fdt.errors import FDTInputError

__all__ = [
    "ACQUISITION_JSON",
    "IMAGES_NAME",
    "read_acquisition",
    "write_acquisition",
    "write_json_atomic",
    "write_volume_tiff",
    "write_stack_tiff",
    "read_volume_tiff",
    "report_path",
    "beside",
    "check_report_free",
    "VOLUME_SUFFIXES",
    "read_image_stack",
    "check_fits_in_memory",
]

PathLike = Union[str, "os.PathLike[str]"]

#: Name of the metadata file inside an acquisition folder.
ACQUISITION_JSON = "acquisition.json"
#: Name :func:`write_acquisition` gives the image stack.
IMAGES_NAME = "images.tif"

_TIFF_FIX = "re-export the images as a grayscale TIFF stack of shape (N, H, W), float32 or uint16"

# Length units of OME ``PhysicalSize*Unit``, in µm.
_OME_UNITS_UM = {
    "µm": 1.0, "μm": 1.0, "um": 1.0, "micron": 1.0, "microns": 1.0,
    "nm": 1e-3, "pm": 1e-6, "Å": 1e-4, "mm": 1e3, "cm": 1e4, "m": 1e6,
}


# --------------------------------------------------------------------------- atomic writes


def _temp_sibling(target: Path, tag: str, suffix: str = "") -> Path:
    """A free hidden name next to ``target``: ``.{name}.{tag}-{random}{suffix}``."""
    while True:
        candidate = target.with_name(f".{target.name}.{tag}-{secrets.token_hex(4)}{suffix}")
        if not os.path.lexists(candidate):
            return candidate


def _remove(path: Path) -> None:
    """Delete a file, link or folder tree; silently if it is already gone."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


def _fsync(path: Path) -> None:
    """Flush one file or folder entry to disk (best effort; folders cannot be opened on Windows)."""
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _fsync_output(path: Path) -> None:
    """Flush a written file, or every file of a written folder and the folder itself."""
    if path.is_dir():
        for p in path.rglob("*"):
            if p.is_file():
                _fsync(p)
    _fsync(path)


def _check_target(target: Path, overwrite: bool, directory: bool) -> None:
    kind = "folder" if directory else "file"
    if not os.path.lexists(target):
        return
    if not overwrite:
        raise FDTInputError(
            "path", f"{target} exists", f"choose another {kind} or pass overwrite=True / --overwrite"
        )
    if directory and not target.is_dir():
        raise FDTInputError("path", f"{target} exists and is not a folder", "choose another folder")
    if not directory and target.is_dir():
        raise FDTInputError("path", f"{target} exists and is a folder", "choose another file name")


@contextlib.contextmanager
def _atomic_output(
    path: PathLike, *, overwrite: bool, directory: bool = False, suffix: str = ""
) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success move it into place with ``os.replace``.

    The one mechanism behind every writer. Missing parent folders are created. For a file the
    temporary path does not exist yet (the caller creates it; ``suffix`` is appended to its name,
    e.g. ``".ome.tif"`` for writers that look at the suffix). For a folder it is an empty folder.
    An existing target is refused unless ``overwrite``; a file is then replaced atomically, a
    folder is moved aside to a temporary sibling, the new one moved in, and the old one deleted,
    so that an interruption never leaves a half folder at ``path``. On error the temporary
    output is deleted and the target left as it was; an ``OSError`` (a full disk, a folder that became
    unwritable) becomes an :class:`FDTInputError` naming the path and saying the previous output is unchanged.
    """
    target = Path(path)
    if not target.name or target.name in (".", ".."):
        raise FDTInputError("path", f"{str(path)!r} does not name a file or folder", "give a full path")
    _check_target(target, overwrite, directory)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FDTInputError(
            "path", f"cannot create folder {target.parent}: {exc}", "choose a writable location"
        ) from exc
    tmp = _temp_sibling(target, "tmp", suffix)
    if directory:
        tmp.mkdir()
    try:
        yield tmp
        _fsync_output(tmp)
        _check_target(target, overwrite, directory)  # something may have appeared meanwhile
        if directory and os.path.lexists(target):
            old = _temp_sibling(target, "old")
            os.replace(target, old)
            try:
                os.replace(tmp, target)
            except BaseException:
                os.replace(old, target)
                raise
            _remove(old)
        else:
            os.replace(tmp, target)
    except OSError as exc:  # a full disk, a folder that became unwritable: the target stays as it was
        _remove(tmp)
        before = "the previous one is unchanged" if os.path.lexists(target) else "nothing was written"
        raise FDTInputError("path", f"could not write {target}: {exc.strerror or exc} ({before})",
                            "free space on that disk or choose a writable location") from exc
    except BaseException:
        _remove(tmp)
        raise
    _fsync(target.parent)


#: Endings of volume files and folders that :func:`report_path` replaces by ``.json`` (longest first).
VOLUME_SUFFIXES = (".ome.tiff", ".ome.tif", ".ome.zarr", ".tiff", ".tif", ".zarr")


def beside(volume_path: PathLike, tag: str) -> Path:
    """A companion volume's name: ``_tag`` before the volume ending (``RI.tif`` → ``RI_bounds.tif``, ``RI.ome.zarr``
    → ``RI_tv3.ome.zarr``); a name without a volume ending keeps its last suffix."""
    p = Path(volume_path)
    name = p.name
    suffix = next((s for s in VOLUME_SUFFIXES if name.lower().endswith(s) and len(name) > len(s)), p.suffix)
    return p.with_name(f"{name[: len(name) - len(suffix)]}_{tag}{suffix}")


def report_path(volume_path: PathLike) -> Path:
    """The report beside a volume: the full name with its volume ending replaced by ``.json``.

    ``RI.tif`` / ``RI.ome.tif`` / ``RI.ome.zarr`` → ``RI.json``; ``RI_lr0.05.tif`` → ``RI_lr0.05.json``
    (every dot before the ending is kept, so distinct names get distinct reports); a name without a volume
    ending gets ``.json`` appended. Two outputs that differ only in their ending (``RI.tif``, ``RI.ome.tif``)
    share a name: :func:`check_report_free` refuses the second while the first exists.
    """
    p = Path(volume_path)
    name, low = p.name, p.name.lower()
    for suffix in VOLUME_SUFFIXES:
        if low.endswith(suffix) and len(name) > len(suffix):
            return p.with_name(name[: -len(suffix)] + ".json")
    return p.with_name(name + ".json")


def check_report_free(volume_path: PathLike) -> None:
    """Refuse a report target that holds the report of *another* volume that still exists.

    ``RI.tif`` and ``RI.ome.tif`` share ``RI.json``: writing the second would silently replace the first's
    report even with ``overwrite`` (which replaces this output, not another's). Reads only the JSON's
    ``output``; a missing, unreadable or foreign file is not in the way of the usual overwrite rules.
    """
    volume = Path(volume_path)
    side = report_path(volume)
    if not side.is_file():
        return
    try:
        data = json.loads(side.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return
    if not isinstance(data, dict) or data.get("format") != "napari-fdt-report" or not isinstance(data.get("output"), str):
        return
    other = Path(data["output"])
    if not other.is_absolute():
        other = side.parent / other
    if other.name != volume.name and other.parent.resolve() == volume.parent.resolve() and os.path.lexists(other):
        raise FDTInputError("out", f"{side} is the report of {other.name}, which would lose it",
                            f"choose another output name than {volume.name}, e.g. with _2 before its ending")


def write_json_atomic(path: PathLike, obj: Any, *, overwrite: bool = False) -> Path:
    """Write ``obj`` as UTF-8 JSON (indent 1) to ``path`` atomically; refuse an existing file unless ``overwrite``."""
    try:
        text = json.dumps(obj, indent=1, ensure_ascii=False) + "\n"
    except (TypeError, ValueError) as exc:
        raise FDTInputError(
            "json", f"cannot be written as JSON: {exc}", "use only dicts, lists, str, numbers, bool, None"
        ) from exc
    with _atomic_output(path, overwrite=overwrite) as tmp:
        with open(tmp, "x", encoding="utf-8") as fh:
            fh.write(text)
    return Path(path)


# --------------------------------------------------------------------------- acquisition folder


def write_acquisition(acq: Acquisition, path: PathLike, *, overwrite: bool = False) -> Path:
    """Write ``acq`` as an acquisition folder (``acquisition.json`` + ``images.tif``) at ``path``.

    The folder is built as a hidden temporary sibling and moved into place, so ``path`` holds
    either nothing/the old folder or the complete new one. Images are written as an ``(N, H, W)``
    TIFF stack in their dtype (float32 or uint16). Returns ``path``.

    Raises
    ------
    FDTInputError
        ``path`` exists and ``overwrite`` is false (the existing folder is left untouched), or
        ``acq.extra`` cannot be written as JSON.
    """
    if not isinstance(acq, Acquisition):
        raise FDTInputError(
            "acquisition", f"must be an Acquisition, got {type(acq).__name__}", "build one with Acquisition(...)"
        )
    try:
        text = json.dumps(acq.to_metadata(IMAGES_NAME), indent=1, ensure_ascii=False) + "\n"
    except (TypeError, ValueError) as exc:
        raise FDTInputError("extra", f"cannot be written as JSON: {exc}", "keep only JSON values in extra") from exc
    with _atomic_output(path, overwrite=overwrite, directory=True) as tmp:
        tifffile.imwrite(tmp / IMAGES_NAME, acq.images, photometric="minisblack")
        with open(tmp / ACQUISITION_JSON, "x", encoding="utf-8") as fh:
            fh.write(text)
    return Path(path)


def _locate(path: PathLike) -> tuple[Path, Path]:
    """``(folder, acquisition.json path)`` from a folder or the path of its JSON file."""
    p = Path(path)
    if p.is_dir():
        json_path = p / ACQUISITION_JSON
        if not json_path.is_file():
            raise FDTInputError(
                ACQUISITION_JSON, f"not found in {p}",
                "give the acquisition folder: it holds acquisition.json next to the images",
            )
        return p, json_path
    if p.is_file():
        if p.suffix.lower() != ".json":
            raise FDTInputError(
                "path", f"{p} is a file, not an acquisition folder",
                "give the folder holding acquisition.json, or acquisition.json itself",
            )
        return p.parent, p
    if p.name == ACQUISITION_JSON and p.parent.is_dir():
        raise FDTInputError(ACQUISITION_JSON, f"not found in {p.parent}", "check the path")
    raise FDTInputError("path", f"folder {p} does not exist", "check the path of the acquisition folder")


def _reject_duplicate_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    obj: dict[str, Any] = {}
    for key, value in pairs:
        if key in obj:
            raise FDTInputError(key, "appears twice in acquisition.json", "keep one of them")
        obj[key] = value
    return obj


def _read_json(json_path: Path) -> dict[str, Any]:
    name = ACQUISITION_JSON
    try:
        text = json_path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise FDTInputError(name, f"is not UTF-8 text: {exc}", "save it as UTF-8 JSON") from exc
    except OSError as exc:
        raise FDTInputError(name, f"cannot be read: {exc}", "check the file's permissions") from exc
    try:
        metadata = json.loads(text, object_pairs_hook=_reject_duplicate_keys)
    except json.JSONDecodeError as exc:
        raise FDTInputError(
            name, f"is not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}",
            "fix the JSON syntax (a JSON validator shows the spot)",
        ) from exc
    if not isinstance(metadata, dict):
        raise FDTInputError(
            name, f"top level must be a JSON object, got {type(metadata).__name__}",
            'write an object: {"format": "fdt-acquisition", "version": 1, ...}',
        )
    return metadata


def _images_path(folder: Path, metadata: dict[str, Any]) -> tuple[str, Path]:
    """The ``images`` entry and the TIFF path it names, which must lie inside ``folder``."""
    fix = 'write "images": "images.tif", the name of the TIFF stack next to acquisition.json'
    if "images" not in metadata:
        raise FDTInputError("images", "is missing", fix)
    name = metadata["images"]
    if not isinstance(name, str) or not name.strip():
        raise FDTInputError("images", f"must be a file name, got {name!r}", fix)
    posix, windows = PurePosixPath(name), PureWindowsPath(name)
    if posix.is_absolute() or windows.is_absolute() or windows.drive or windows.root:
        raise FDTInputError("images", f"{name!r} is an absolute path", "give a path relative to the acquisition folder")
    if ".." in posix.parts or ".." in windows.parts:
        raise FDTInputError(
            "images", f"{name!r} leaves the acquisition folder", "keep the images inside the acquisition folder"
        )
    image_path = folder / name
    if not image_path.is_file():
        what = "is a folder" if image_path.is_dir() else "not found"
        raise FDTInputError(
            "images", f"{name} {what} in {folder}", "put the TIFF stack next to acquisition.json or fix the images key"
        )
    return name, image_path


@contextlib.contextmanager
def _quiet_tifffile() -> Iterator[None]:
    """tifffile logs what it finds wrong in a file; the readers report it once, as an :class:`FDTInputError`."""
    log = logging.getLogger("tifffile")
    level = log.level
    log.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        log.setLevel(level)


def check_fits_in_memory(name: str, shape: tuple[int, int, int], dtype: Any) -> None:
    """Refuse, from the TIFF's header alone, a stack that could not be held in memory (twice: read and a float copy)."""
    from napari_fdt.device import available_bytes

    n, h, w = shape
    need = 2 * n * h * w * max(np.dtype(dtype).itemsize, 4)  # the pixels, and the float32 copy every run makes
    free = available_bytes("cpu")
    if free is not None and need > 0.9 * free:
        gib = 2.0**30
        raise FDTInputError(
            "images", f"{name} holds {n} images of {h} x {w} px ({np.dtype(dtype)}): about {need / gib:.1f} GiB with "
            f"the float32 copy, and {free / gib:.1f} GiB of memory are free",
            "crop or bin the images, or reconstruct a subset of them",
        )


def read_image_stack(image_path: PathLike, name: str, sources: np.ndarray | None = None) -> np.ndarray:
    """Pixels of the first TIFF series; shape, pixel type, source count and memory checked from the header first.

    Where the file stores them uncompressed and contiguous (what :func:`write_acquisition` and most acquisition
    software write) they come back as a read-only memory map (:mod:`napari_fdt.data.mapped`): nothing is read until
    used, and the input cannot be changed through them. Otherwise they are read into memory.

    Every problem is an :class:`FDTInputError` naming ``images`` (``name`` is the file name shown).
    """
    image_path = Path(image_path)
    try:
        with _quiet_tifffile(), tifffile.TiffFile(image_path) as tif:
            if not tif.series:
                raise FDTInputError("images", f"{name} holds no images", _TIFF_FIX)
            series = tif.series[0]
            if series.axes.endswith("S"):  # interleaved colour; planar "SYX" is read as a stack
                raise FDTInputError(
                    "images", f"{name} holds colour (RGB) images, axes {series.axes}, shape {series.shape}", _TIFF_FIX
                )
            n, h, w = check_image_layout(series.shape, series.dtype)
            if sources is not None:
                check_sources(sources, n)
            mapped = map_series(image_path, series)
            if mapped is not None:  # pixels read when used (chunked checks, the solver's float32 copy)
                return mapped
            check_fits_in_memory(name, (n, h, w), series.dtype)
            return series.asarray()
    except FDTInputError:
        raise
    except MemoryError as exc:  # the estimate passed but the allocation did not
        raise FDTInputError("images", f"{name}: not enough memory to read {series.shape} {series.dtype}",
                            "crop or bin the images, or reconstruct a subset of them") from exc
    except Exception as exc:  # tifffile raises many kinds on corrupt or truncated files
        raise FDTInputError("images", f"{name} is not a readable TIFF: {exc}", _TIFF_FIX) from exc


def read_acquisition(path: PathLike) -> Acquisition:
    """Read an acquisition folder (or the path of its ``acquisition.json``).

    All metadata (format, version, optics, sources, image shape and pixel type) are checked
    before the pixels are loaded. The input is only read.

    Returns
    -------
    The :class:`~napari_fdt.data.acquisition.Acquisition`, images ``(N, H, W)`` float32 or uint16: a read-only memory
    map of the file where it stores them uncompressed (:func:`read_image_stack`; ``numpy.array(acq.images)`` for a
    copy to edit).

    Raises
    ------
    FDTInputError
        Naming the offending field: ``path``, ``acquisition.json``, ``format``, ``version``, an
        optics field, ``sources_um`` / ``sources_um[i]`` or ``images``.
    """
    folder, json_path = _locate(path)
    metadata = _read_json(json_path)
    optics, sources, extra = parse_metadata(metadata)
    name, image_path = _images_path(folder, metadata)
    images = read_image_stack(image_path, name, sources)
    return Acquisition(images=images, optics=optics, sources_um=sources, extra=extra)


# --------------------------------------------------------------------------- volumes


def _voxel_size(voxel_size_um: Any) -> tuple[float, float, float]:
    fix = "give (dz, dy, dx) in µm, each > 0"
    try:
        values = tuple(float(v) for v in voxel_size_um)
    except (TypeError, ValueError) as exc:
        raise FDTInputError("voxel_size_um", f"must be three numbers, got {voxel_size_um!r}", fix) from exc
    if len(values) != 3 or not all(np.isfinite(v) and v > 0 for v in values):
        raise FDTInputError("voxel_size_um", f"must be three positive finite numbers, got {voxel_size_um!r}", fix)
    return values  # type: ignore[return-value]


def _finite_float32_volume(volume: Any, field_name: str) -> np.ndarray:
    if not isinstance(volume, np.ndarray) or volume.dtype.kind not in "iuf":
        kind = volume.dtype if isinstance(volume, np.ndarray) else type(volume).__name__
        raise FDTInputError(field_name, f"must be a real numeric array, got {kind}", "give a float32 (Z, Y, X) array")
    if volume.ndim != 3:
        raise FDTInputError(field_name, f"must be 3-D (Z, Y, X), got shape {volume.shape}", "give a (Z, Y, X) volume")
    vol = volume.astype(np.float32, copy=False)
    finite = np.isfinite(vol)
    if not finite.all():
        z, y, x = np.unravel_index(int(np.argmax(~finite)), vol.shape)
        raise FDTInputError(
            field_name,
            f"{int((~finite).sum())} non-finite voxels (NaN or Inf, or beyond float32), "
            f"first at z={z}, y={y}, x={x}",
            "the volume must be finite everywhere",
        )
    return vol


def write_volume_tiff(
    path: PathLike,
    volume: np.ndarray,
    voxel_size_um: tuple[float, float, float],
    *,
    overwrite: bool = False,
) -> Path:
    """Write a ``(Z, Y, X)`` volume as a float32 OME-TIFF, atomically.

    ``voxel_size_um`` is ``(dz, dy, dx)`` in µm, stored as OME ``PhysicalSizeZ/Y/X`` with unit
    ``µm``. Refuses an existing file unless ``overwrite``. Returns ``path``.
    """
    vol = _finite_float32_volume(volume, "volume")
    dz, dy, dx = _voxel_size(voxel_size_um)
    metadata = {
        "axes": "ZYX",
        "PhysicalSizeZ": dz, "PhysicalSizeZUnit": "µm",
        "PhysicalSizeY": dy, "PhysicalSizeYUnit": "µm",
        "PhysicalSizeX": dx, "PhysicalSizeXUnit": "µm",
    }
    with _atomic_output(path, overwrite=overwrite, suffix=".ome.tif") as tmp:
        tifffile.imwrite(tmp, vol, ome=True, photometric="minisblack", metadata=metadata)
    return Path(path)


def write_stack_tiff(path: PathLike, images: np.ndarray, pixel_size_um: float, *, overwrite: bool = False) -> Path:
    """Write an ``(N, H, W)`` image stack (e.g. predicted images) as a float32 OME-TIFF, atomically.

    Axes ``TYX`` (the image index is no z axis: the file is not taken for an RI volume) with ``PhysicalSizeX/Y``
    = ``pixel_size_um`` in µm, which :mod:`napari_fdt.data.microscope` reads back. Refuses an existing file
    unless ``overwrite``.
    """
    stack = np.asarray(images, dtype=np.float32)
    if stack.ndim != 3:
        raise FDTInputError("images", f"must be a stack (N, H, W), got shape {stack.shape}", "give an (N, H, W) array")
    dx = _voxel_size((1.0, pixel_size_um, pixel_size_um))[2]
    metadata = {"axes": "TYX", "PhysicalSizeY": dx, "PhysicalSizeYUnit": "µm", "PhysicalSizeX": dx, "PhysicalSizeXUnit": "µm"}
    with _atomic_output(path, overwrite=overwrite, suffix=".ome.tif") as tmp:
        tifffile.imwrite(tmp, stack, ome=True, photometric="minisblack", metadata=metadata)
    return Path(path)


def _ome_voxel_size(ome_xml: str | None) -> tuple[float, float, float] | None:
    """``(dz, dy, dx)`` in µm from the first OME ``Pixels`` element, or None if incomplete."""
    if not ome_xml:
        return None
    try:
        root = ET.fromstring(ome_xml)
    except ET.ParseError:
        return None
    pixels = next((el for el in root.iter() if el.tag.rsplit("}", 1)[-1] == "Pixels"), None)
    if pixels is None:
        return None
    sizes = []
    for axis in "ZYX":
        value = pixels.get(f"PhysicalSize{axis}")
        scale = _OME_UNITS_UM.get(pixels.get(f"PhysicalSize{axis}Unit", "µm"))  # OME default: µm
        try:
            size = float(value) * scale  # type: ignore[arg-type, operator]
        except (TypeError, ValueError):
            return None
        if not (np.isfinite(size) and size > 0):
            return None
        sizes.append(size)
    return sizes[0], sizes[1], sizes[2]


def read_volume_tiff(path: PathLike) -> tuple[np.ndarray, tuple[float, float, float] | None]:
    """Read a 3-D volume from a TIFF (OME or not).

    Returns
    -------
    ``(volume, voxel_size_um)``: the ``(Z, Y, X)`` float32 volume and ``(dz, dy, dx)`` in µm from
    the OME metadata, or ``None`` where the file does not give all three.

    Raises
    ------
    FDTInputError
        Named after the file, if it is missing, not a readable TIFF, not 3-D or not finite.
    """
    p = Path(path)
    field_name = p.name or str(p)
    if not p.is_file():
        what = "is a folder" if p.is_dir() else "not found"
        raise FDTInputError(field_name, f"{p} {what}", "check the path of the volume TIFF")
    try:
        with _quiet_tifffile(), tifffile.TiffFile(p) as tif:
            if not tif.series:
                raise FDTInputError(field_name, "holds no images", "give a (Z, Y, X) TIFF volume")
            series = tif.series[0]
            shape = tuple(series.shape)
            if len(shape) != 3:
                # OME squeezes a single slice away: keep Z, Y, X even where they have length 1.
                full = zip(series.get_shape(False), series.get_axes(False))
                unsqueezed = tuple(s for s, a in full if s > 1 or a in "ZYX")
                if tif.is_ome and len(unsqueezed) == 3:
                    shape = unsqueezed
            if len(shape) != 3:
                raise FDTInputError(
                    field_name, f"must be a 3-D (Z, Y, X) volume, got shape {series.shape} (axes {series.axes})",
                    "give a single-channel (Z, Y, X) TIFF volume",
                )
            if np.dtype(series.dtype).kind not in "iuf":
                raise FDTInputError(field_name, f"pixel type {series.dtype} is not real", "give a float32 volume")
            raw = series.asarray().reshape(shape)
            ome = tif.ome_metadata if tif.is_ome else None
    except FDTInputError:
        raise
    except MemoryError as exc:
        raise FDTInputError(field_name, f"not enough memory to read a volume of shape {series.shape}",
                            "crop the volume") from exc
    except Exception as exc:  # tifffile raises many kinds on corrupt or truncated files
        raise FDTInputError(field_name, f"is not a readable TIFF: {exc}", "re-export the volume as a TIFF") from exc
    return _finite_float32_volume(raw, field_name), _ome_voxel_size(ome)
