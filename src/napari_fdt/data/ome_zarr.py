"""RI volumes as OME-Zarr (OME-NGFF 0.4): axes z, y, x in micrometre, scale and translation, one resolution level.

The layout is that of the NGFF 0.4 specification (https://ngff.openmicroscopy.org/0.4/), read by
napari-ome-zarr and ome-zarr-py:

* a Zarr (format 2) group whose ``.zattrs`` hold ``multiscales``: version ``"0.4"``, axes
  ``z, y, x`` of type ``space`` and unit ``micrometer``, one dataset ``"0"`` with the coordinate
  transformations ``scale = (dz, dy, dx)`` and ``translation`` = the position of voxel (0, 0, 0)'s centre,
  ``(dz/2, −(H//2)·dy, −(W//2)·dx)`` µm: the image-centred origin of ``docs/format.md`` (z = 0 at the
  volume's bottom face);
* the array ``0``: the absolute RI, float32, shape ``(n_slices, H, W)``, one chunk per slice;
* ``napari_fdt``: ``{"kind": "ri", "version": 1}`` in the group's attributes, marking a napari-fdt volume.

The folder is built under a temporary name and moved into place (never half-written). Needs the optional
``zarr`` package (``pip install "napari-fdt[zarr]"``); the rest of the core imports without it.
NGFF 0.5 (Zarr format 3, attributes under ``"ome"``) is read as well.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from napari_fdt.data.io import PathLike, _atomic_output, _finite_float32_volume, _voxel_size, report_path
from napari_fdt.errors import FDTInputError

__all__ = ["ZARR_SUFFIXES", "has_zarr", "is_ome_zarr", "write_volume_zarr", "read_volume_zarr", "ngff_multiscales"]

#: Folder name endings written and read as OME-Zarr.
ZARR_SUFFIXES = (".ome.zarr", ".zarr")
_MARK = {"kind": "ri", "version": 1}
_INSTALL = 'install the zarr package: pip install "napari-fdt[zarr]"'


def has_zarr() -> bool:
    """Whether the optional ``zarr`` package is importable."""
    try:
        import zarr  # noqa: F401
    except ImportError:
        return False
    return True


def _zarr():
    try:
        import zarr
    except ImportError as exc:
        raise FDTInputError("zarr", "OME-Zarr needs the zarr package, which is not installed", _INSTALL) from exc
    return zarr


def ngff_multiscales(shape: tuple[int, int, int], voxel_size_um: tuple[float, float, float], name: str) -> list[dict[str, Any]]:
    """The NGFF 0.4 ``multiscales`` attribute of one ``(Z, Y, X)`` level with the image-centred origin."""
    dz, dy, dx = (float(v) for v in voxel_size_um)
    _, h, w = shape
    return [{
        "version": "0.4",
        "name": name,
        "axes": [{"name": a, "type": "space", "unit": "micrometer"} for a in "zyx"],
        "datasets": [{"path": "0", "coordinateTransformations": [
            {"type": "scale", "scale": [dz, dy, dx]},
            {"type": "translation", "translation": [0.5 * dz, -(h // 2) * dy, -(w // 2) * dx]},
        ]}],
        "type": "none",
        "metadata": {"description": "absolute refractive index, slice 0 nearest the sources (napari-fdt, docs/format.md)"},
    }]


def write_volume_zarr(path: PathLike, volume: np.ndarray, voxel_size_um: tuple[float, float, float], *,
                      overwrite: bool = False, name: str | None = None) -> Path:
    """Write a ``(Z, Y, X)`` RI volume as an OME-Zarr folder (NGFF 0.4), atomically; returns ``path``.

    ``voxel_size_um`` is ``(dz, dy, dx)`` in µm. Refuses an existing folder unless ``overwrite``.
    """
    zarr = _zarr()
    vol = _finite_float32_volume(volume, "volume")
    voxel = _voxel_size(voxel_size_um)
    target = Path(path)
    attrs = {"multiscales": ngff_multiscales(vol.shape, voxel, name or report_path(target).stem), "napari_fdt": dict(_MARK)}
    chunks = (1, *vol.shape[1:])
    with _atomic_output(target, overwrite=overwrite, directory=True) as tmp:
        if int(zarr.__version__.split(".")[0]) >= 3:
            root = zarr.open_group(str(tmp), mode="w", zarr_format=2)
            arr = root.create_array("0", shape=vol.shape, chunks=chunks, dtype="float32",
                                     chunk_key_encoding={"name": "v2", "separator": "/"})
            arr[...] = vol
        else:  # zarr 2 (Python 3.10)
            root = zarr.open_group(str(tmp), mode="w")
            root.create_dataset("0", data=vol, chunks=chunks, dtype="float32", dimension_separator="/")
        root.attrs.update(attrs)
    return target


def _group_attrs(folder: Path) -> dict[str, Any] | None:
    """The group attributes of a Zarr folder from its JSON alone (format 2 ``.zattrs`` or format 3 ``zarr.json``)."""
    for name in (".zattrs", "zarr.json"):
        f = folder / name
        if f.is_file():
            try:
                data = json.loads(f.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                return None
            if not isinstance(data, dict):
                return None
            return data.get("attributes", {}) if name == "zarr.json" else data
    return None


def _multiscales(attrs: dict[str, Any]) -> list[dict[str, Any]] | None:
    ome = attrs.get("ome") if isinstance(attrs.get("ome"), dict) else {}
    ms = attrs.get("multiscales", ome.get("multiscales"))
    return ms if isinstance(ms, list) and ms and isinstance(ms[0], dict) else None


def is_ome_zarr(path: PathLike, *, ours: bool = True) -> bool:
    """Whether ``path`` is an OME-Zarr image with 3 spatial axes (written by napari-fdt, when ``ours``), from its JSON."""
    p = Path(path)
    if not p.is_dir():
        return False
    attrs = _group_attrs(p)
    if attrs is None:
        return False
    ms = _multiscales(attrs)
    if ms is None:
        return False
    axes = ms[0].get("axes")
    if not (isinstance(axes, list) and len(axes) == 3):
        return False
    ome = attrs.get("ome") if isinstance(attrs.get("ome"), dict) else {}
    return not ours or attrs.get("napari_fdt", ome.get("napari_fdt")) == _MARK


#: Codecs an RI array may be stored with: compressors, checksums and numeric filters. Anything else is refused before
#: zarr opens the array: the "pickle" codec (numcodecs.Pickle, read by zarr 2) would unpickle each chunk, and so run
#: code a file carries.
SAFE_CODECS = frozenset({"blosc", "zstd", "gzip", "zlib", "lz4", "bz2", "lzma", "crc32c", "bytes", "endian", "transpose",
                         "shuffle", "delta", "fixedscaleoffset", "quantize", "bitround", "packbits", "astype",
                         "sharding_indexed", "fletcher32", "jenkins_lookup3", "adler32", "crc32"})


def _codec_names(meta: Any) -> list[str]:
    """The codec ids (format 2: ``{"id": ...}``) or names (format 3: ``{"name": ..., "configuration": ...}``, sharding's
    inner codecs included) in ``meta`` (a codec, a list of them or None), without numcodecs' ``numcodecs.`` prefix."""
    if isinstance(meta, list):
        return [n for m in meta for n in _codec_names(m)]
    if not isinstance(meta, dict):
        return []
    ident = meta.get("id", meta.get("name"))
    names = [ident.removeprefix("numcodecs.")] if isinstance(ident, str) else ["(unnamed)"]
    conf = meta.get("configuration")
    if isinstance(conf, dict):
        names += _codec_names(conf.get("codecs")) + _codec_names(conf.get("index_codecs"))
    return names


def _check_array_metadata(folder: Path, field_name: str) -> None:
    """Refuse an array whose JSON metadata names a data type other than numbers or a codec not in :data:`SAFE_CODECS`,
    before zarr reads any of it (FDTInputError naming the field)."""
    for name, fmt in ((".zarray", 2), ("zarr.json", 3)):
        f = folder / name
        if not f.is_file():
            continue
        try:
            meta = json.loads(f.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise FDTInputError(field_name, f"its array metadata {f} cannot be read: {exc}", "check the folder is a complete OME-Zarr image") from None
        dtype = meta.get("dtype") if fmt == 2 else meta.get("data_type")
        try:
            kind = np.dtype(dtype).kind if isinstance(dtype, str) else "O"
        except TypeError:
            kind = "O"
        if kind not in "biuf":
            raise FDTInputError(field_name, f"its array holds {dtype!r} data, not numbers", "give an RI volume of numbers (float32)")
        unknown = sorted(set(_codec_names([meta.get(k) for k in ("compressor", "filters", "codecs")])) - SAFE_CODECS)
        if unknown:
            raise FDTInputError(field_name, f"its array is stored with codec(s) {', '.join(unknown)}, which napari-fdt does not "
                                "read (a pickle codec would run code from the file)", "write it again with a standard compressor (zstd, blosc)")
        return


_UNITS_UM = {"micrometer": 1.0, "nanometer": 1e-3, "millimeter": 1e3, "meter": 1e6, "angstrom": 1e-4, None: 1.0}


def read_volume_zarr(path: PathLike) -> tuple[np.ndarray, tuple[float, float, float], tuple[float, float, float]]:
    """Read the full-resolution level of an OME-Zarr ``(Z, Y, X)`` image.

    Returns ``(volume float32, voxel_size_um (dz, dy, dx), translation_um (z, y, x))``: the scale and
    translation of dataset 0 (multiplied by any multiscale-wide transformation), in µm.
    """
    p = Path(path)
    field_name = p.name or str(p)
    attrs = _group_attrs(p) if p.is_dir() else None
    ms = _multiscales(attrs) if attrs is not None else None
    if ms is None:
        raise FDTInputError(field_name, f"{p} is not an OME-Zarr image (no multiscales metadata)", "give an .ome.zarr folder")
    m = ms[0]
    axes = m.get("axes") or []
    if len(axes) != 3 or any(isinstance(a, dict) and a.get("type") not in (None, "space") for a in axes):
        raise FDTInputError(field_name, f"has axes {axes}, not three spatial axes (z, y, x)", "give a single-channel 3-D volume")
    units = [_UNITS_UM.get(a.get("unit") if isinstance(a, dict) else None) for a in axes]
    if any(u is None for u in units):
        raise FDTInputError(field_name, f"has an axis unit this reader does not know: {axes}", "write the axes in micrometer")
    dataset = m["datasets"][0]
    scale, translation = np.ones(3), np.zeros(3)
    for transforms in (dataset.get("coordinateTransformations", []), m.get("coordinateTransformations", [])):
        for t in transforms:
            if t.get("type") == "scale":
                scale = scale * np.asarray(t["scale"], dtype=float)
                translation = translation * np.asarray(t["scale"], dtype=float)
            elif t.get("type") == "translation":
                translation = translation + np.asarray(t["translation"], dtype=float)
    _check_array_metadata(p / dataset["path"], field_name)
    zarr = _zarr()
    try:
        arr = zarr.open_array(str(p / dataset["path"]), mode="r")
        raw = np.asarray(arr[...])
    except Exception as exc:  # zarr raises many kinds on damaged stores
        raise FDTInputError(field_name, f"cannot be read: {exc}", "check the folder is a complete OME-Zarr image") from exc
    u = np.asarray(units, dtype=float)
    vol = _finite_float32_volume(raw, field_name)
    voxel = tuple(float(v) for v in scale * u)
    return vol, voxel, tuple(float(v) for v in translation * u)  # type: ignore[return-value]
