"""Image stacks held as read-only memory maps of their TIFF file, and work on them in chunks.

A full-size acquisition (1521 images of 512×512 px, 0.8 GB as uint16) is opened without reading its pixels: the
stack is a :class:`numpy.memmap` of the file's pixel data (where the TIFF stores it uncompressed, in order and in
the machine's byte order), so ``fdt info``, the napari reader and the acquisition widget touch only what they show.
What must see every pixel (the checks for NaN and negative values, the mean, the float32 rows the solver trains on)
goes through the stack in chunks of :data:`CHUNK_BYTES`, so it never holds a temporary of the stack's size.

A mapped stack crosses to another process (the napari plugin's computation) as its file reference
(:class:`MappedFile`), not as a copy of its pixels; the other process maps the same file.
"""

from __future__ import annotations

import mmap
import os
from dataclasses import dataclass
from typing import Iterator

import numpy as np

__all__ = ["CHUNK_BYTES", "MappedFile", "chunks", "map_series", "mapped_file", "scaled_float32", "mean_of"]

#: Largest temporary a chunked pass over a stack makes (bytes of float32).
CHUNK_BYTES = 64 * 2**20


def chunks(images: np.ndarray, chunk_bytes: int | None = None) -> Iterator[slice]:
    """Slices along the first axis of ``images`` (N, H, W) whose float32 form stays under ``chunk_bytes``
    (default :data:`CHUNK_BYTES`)."""
    chunk_bytes = CHUNK_BYTES if chunk_bytes is None else int(chunk_bytes)
    n = int(images.shape[0])
    per_image = max(1, int(np.prod(images.shape[1:], dtype=np.int64)) * 4)
    step = max(1, chunk_bytes // per_image)
    for start in range(0, n, step):
        yield slice(start, min(n, start + step))


def mean_of(images: np.ndarray) -> float:
    """Mean of all pixels of ``images`` (N, H, W), accumulated in float64 chunk by chunk."""
    total = 0.0
    for s in chunks(images):
        total += float(images[s].sum(dtype=np.float64))
    return total / max(1, images.size)


def scaled_float32(images: np.ndarray, scale: float) -> np.ndarray:
    """``images / scale`` as a new float32 array, filled chunk by chunk (one array of the stack's size, no temporaries)."""
    out = np.empty(images.shape, dtype=np.float32)
    for s in chunks(images):
        np.divide(images[s], scale, out=out[s], dtype=np.float32, casting="unsafe")
    return out


def map_series(path: os.PathLike | str, series) -> np.memmap | None:
    """The pixels of a tifffile ``series`` as a read-only memory map, or None where they cannot be mapped
    (compressed, tiled or scattered over the file, another byte order, or empty)."""
    offset = getattr(series, "dataoffset", None)
    if offset is None or not series.dtype.isnative or int(np.prod(series.shape)) == 0:
        return None
    try:
        return np.memmap(path, dtype=series.dtype, mode="r", offset=int(offset), shape=tuple(series.shape))
    except (OSError, ValueError):  # a file shorter than its header says, or a filesystem without mmap
        return None


@dataclass(frozen=True)
class MappedFile:
    """Where a memory-mapped array's pixels lie: file, byte offset, type and shape (C order)."""

    filename: str
    offset: int
    dtype: str
    shape: tuple[int, ...]

    def open(self) -> np.memmap:
        """Map the file again, read-only."""
        return np.memmap(self.filename, dtype=np.dtype(self.dtype), mode="r", offset=self.offset, shape=self.shape)


def mapped_file(array: np.ndarray) -> MappedFile | None:
    """The file reference of a C-contiguous read-only memory map (or a contiguous view of one), else None."""
    if not isinstance(array, np.memmap) or array.filename is None or not array.flags.c_contiguous:
        return None
    buffer = getattr(array, "_mmap", None)
    if buffer is None or array.flags.writeable:
        return None
    try:
        map_start = np.frombuffer(buffer, dtype=np.uint8).ctypes.data
    except (TypeError, ValueError):
        return None
    # np.memmap maps from the allocation-granularity boundary below its offset; a view starts further in.
    file_start = array.offset - array.offset % mmap.ALLOCATIONGRANULARITY
    offset = file_start + (array.ctypes.data - map_start)
    return MappedFile(str(array.filename), int(offset), array.dtype.str, tuple(int(s) for s in array.shape))
