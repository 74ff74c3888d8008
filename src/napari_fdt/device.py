"""Where the computation runs, and how much memory it has: the compute device and its free memory.

Bottom layer (beside :mod:`napari_fdt.errors`): every layer above may ask which device ``"auto"`` means and how
many bytes are free there. torch is imported only when a device is resolved or a GPU is asked, so the data layer
can read free host RAM without it.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

from napari_fdt.errors import FDTInputError

if TYPE_CHECKING:
    import torch

__all__ = ["resolve_device", "available_bytes"]


def resolve_device(device: "str | torch.device | None" = "auto") -> "torch.device":
    """``"auto"`` → CUDA when available, else CPU; otherwise ``torch.device(device)``.

    Raises :class:`FDTInputError` (field ``device``) when CUDA is asked for and none is present.
    """
    import torch

    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise FDTInputError("device", "CUDA was requested but no CUDA device is available", "use --device cpu or auto")
    return dev


def available_bytes(device: "str | torch.device" = "cpu") -> int | None:
    """Free memory on ``device`` in bytes (CUDA: free device memory; CPU: available RAM on Linux), or None."""
    if str(getattr(device, "type", device)).startswith("cuda"):
        import torch

        free, _ = torch.cuda.mem_get_info(device)
        return int(free)
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None
