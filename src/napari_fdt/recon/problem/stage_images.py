"""The measured images a stage trains on, read batch by batch from the acquisition's array on the CPU.

On the CPU the solver does not copy the stack to float32: :class:`LazyImages` holds the acquisition's array (a
read-only memory map of the file where it is uncompressed, :mod:`napari_fdt.data.mapped`; or the array in memory)
and its normalisation, and converts only the rows a batch asks for, with the same float32 operation a whole-stack
copy would use (the results are bit-identical). A 1521×512² uint16 stack then costs its file pages, not 1.6 GB of
float32. Coarse stages average their blocks chunk by chunk into a small tensor; a GPU stage gets the whole
normalised stack on the device (chunk by chunk, without a CPU copy of its size).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from napari_fdt.data.mapped import chunks, scaled_float32

__all__ = ["LazyImages", "stage_images", "block_average", "stays_on_host"]


def block_average(images: torch.Tensor, factor: int) -> torch.Tensor:
    """Average (..., H, W) over factor×factor blocks → (..., H//f, W//f); the remainder rows/columns are dropped."""
    if factor == 1:
        return images
    shape = images.shape
    flat = images.reshape(-1, 1, shape[-2], shape[-1])
    out = F.avg_pool2d(flat, factor, stride=factor)
    return out.reshape(*shape[:-2], out.shape[-2], out.shape[-1])


class LazyImages:
    """(N, H, W) float32 images ``array / scale`` (``array``: numpy (N, H, W), any real pixel type), read on indexing.

    Supports what the solver does with a stage's images: ``images[idx]`` (a 1-D index tensor, list or array → a
    float32 tensor (B, H, W) on the CPU), ``.shape``, ``.max()``, ``.to(device)`` and :meth:`materialize`.
    """

    dtype = torch.float32
    device = torch.device("cpu")
    ndim = 3

    def __init__(self, array: np.ndarray, scale: float) -> None:
        self.array, self.scale = array, float(scale)
        self._max: torch.Tensor | None = None

    @property
    def shape(self) -> torch.Size:
        return torch.Size(int(s) for s in self.array.shape)

    def __len__(self) -> int:
        return int(self.array.shape[0])

    def _convert(self, rows: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(scaled_float32(rows, self.scale))

    def __getitem__(self, key: Any) -> torch.Tensor:
        if isinstance(key, torch.Tensor):
            key = key.detach().cpu().numpy()
        if isinstance(key, slice):
            return self._convert(np.asarray(self.array[key]))
        idx = np.asarray(key, dtype=np.int64).reshape(-1)
        return self._convert(np.asarray(self.array[idx]))

    def max(self) -> torch.Tensor:
        """The largest normalised pixel (a 0-d tensor), computed once, chunk by chunk."""
        if self._max is None:
            peak = max(float(np.max(self.array[s])) for s in chunks(self.array))
            self._max = self._convert(np.asarray([peak], dtype=np.float64))[0]
        return self._max

    def materialize(self, device: torch.device | str = "cpu") -> torch.Tensor:
        """The whole normalised stack as one tensor on ``device``, converted chunk by chunk."""
        out = torch.empty(tuple(self.shape), dtype=torch.float32, device=device)
        for s in chunks(self.array):
            out[s] = self[s].to(device)
        return out

    def to(self, device: torch.device | str) -> "LazyImages | torch.Tensor":
        """Itself on the CPU; the whole stack as a tensor on another device."""
        return self if stays_on_host(torch.device(device).type) else self.materialize(device)


def stays_on_host(device_type: str) -> bool:
    """Where the measured images live: on the CPU they stay in the acquisition's array (read batch by batch, lazily);
    on another device the whole stack is copied there as float32."""
    return device_type == "cpu"


def stage_images(images: torch.Tensor | LazyImages, height: int, width: int, factor: int,
                 device: torch.device) -> torch.Tensor | LazyImages:
    """A stage's images: ``images`` (N, H, W) cropped to (height·factor, width·factor) and averaged over factor×factor
    blocks, on ``device``. Lazy images stay lazy where nothing is to average on the CPU."""
    if not isinstance(images, LazyImages):
        return block_average(images[:, : height * factor, : width * factor], factor).to(device)
    if factor == 1 and tuple(images.shape[1:]) == (height, width):
        return images.to(device)
    parts = [block_average(images[s][:, : height * factor, : width * factor], factor) for s in chunks(images.array)]
    return torch.cat(parts).to(device)
