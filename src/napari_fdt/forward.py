"""Differentiable multi-slice forward model: point sources → RI volume → camera images.

Geometry (``docs/physics.md``): light travels +z. Sources lie ``depth`` below the volume's bottom
face (z = 0); slice k (k = 0 nearest the sources) fills ``[k·Δz, (k+1)·Δz]`` and acts as a thin phase
screen at its middle (symmetric split step). The exit field at the top face z = T is
back-propagated by ``image_plane_um`` to the camera's focal plane, filtered by the pupil and
detected as ``gain · |E|²``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .grid import GridPlan, frequency_grid
from .optics import Optics
from .propagation import phase_screen, propagation_kernel, pupil
from .sources import band_limit, centering_sign, point_source_spectrum

__all__ = ["MultiSliceModel", "resolve_device"]


def resolve_device(device: str | torch.device | None = "auto") -> torch.device:
    """``"auto"`` → CUDA when available, else CPU; otherwise ``torch.device(device)``."""
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        from .errors import FDTInputError

        raise FDTInputError("device", "CUDA was requested but no CUDA device is available", "use --device cpu or auto")
    return dev


class MultiSliceModel:
    """The forward model for one optics and grid plan; kernels are built once at construction.

    Parameters
    ----------
    optics: optics and sampling.
    plan: the window from :func:`napari_fdt.grid.plan_grid`.
    device: ``"auto"``, ``"cpu"``, ``"cuda"`` or a torch device.
    dtype: real dtype, ``torch.float32`` (complex64 fields, default) or ``torch.float64``.

    Call it as ``model(delta_n, sources_um, gain)`` → images (B, H, W).
    """

    def __init__(self, optics: Optics, plan: GridPlan, *, device: str | torch.device | None = "auto", dtype: torch.dtype = torch.float32) -> None:
        if dtype not in (torch.float32, torch.float64):
            raise ValueError("dtype must be torch.float32 or torch.float64 (fp16 phases are too coarse)")
        self.optics = optics
        self.plan = plan
        self.device = resolve_device(device)
        self.dtype = dtype
        dz = optics.slice_spacing_um
        fy, fx = frequency_grid(plan.padded_shape, optics.pixel_size_um, device=self.device, dtype=dtype)
        self._fy, self._fx = fy, fx
        f2 = fy * fy + fx * fx
        self._window = band_limit(f2, plan.f_lo_per_um, plan.f_hi_per_um)
        self._centering = centering_sign(plan.padded_shape, device=self.device, dtype=dtype)
        self._slice_kernel = propagation_kernel(f2, dz, optics.n_background, optics.wavelength_um)
        exit_distance = 0.5 * dz - optics.image_plane_um  # last screen → camera focal plane
        self._exit_kernel = propagation_kernel(f2, exit_distance, optics.n_background, optics.wavelength_um) * pupil(
            f2, optics.na, optics.wavelength_um, plan.pupil_taper
        )

    # -- pieces -------------------------------------------------------------------------------
    def source_spectrum(self, sources_um: torch.Tensor) -> torch.Tensor:
        """(B, Hp, Wp) spectrum of the sources at the first screen (half a slice above the bottom face)."""
        return point_source_spectrum(
            self._fy,
            self._fx,
            sources_um.to(self.device, self.dtype),
            0.5 * self.optics.slice_spacing_um,
            n_background=self.optics.n_background,
            wavelength_um=self.optics.wavelength_um,
            pixel_size_um=self.optics.pixel_size_um,
            window=self._window,
            centering=self._centering,
        )

    def pad_volume(self, delta_n: torch.Tensor) -> torch.Tensor:
        """Place a (n_slices, H, W) contrast volume in the window (background outside); (n, Hp, Wp) passes through."""
        n = self.optics.n_slices
        hp, wp = self.plan.padded_shape
        h, w = self.plan.image_shape
        delta_n = delta_n.to(self.device, self.dtype)
        if delta_n.ndim != 3 or delta_n.shape[0] != n:
            raise ValueError(f"delta_n must have shape ({n}, H, W), got {tuple(delta_n.shape)}")
        if tuple(delta_n.shape[1:]) == (hp, wp):
            return delta_n
        if tuple(delta_n.shape[1:]) != (h, w):
            raise ValueError(f"delta_n must be ({n}, {h}, {w}) or ({n}, {hp}, {wp}), got {tuple(delta_n.shape)}")
        oy, ox = self.plan.offset
        return F.pad(delta_n, (ox, wp - w - ox, oy, hp - h - oy))

    def crop(self, field: torch.Tensor) -> torch.Tensor:
        """The image region of a (..., Hp, Wp) array."""
        oy, ox = self.plan.offset
        h, w = self.plan.image_shape
        return field[..., oy : oy + h, ox : ox + w]

    def camera_field(self, delta_n: torch.Tensor, sources_um: torch.Tensor) -> torch.Tensor:
        """Complex field at the camera, (B, H, W), for contrast ``delta_n = n − n_b``.

        ``delta_n`` is (n_slices, H, W) on the image grid (background outside) or (n_slices, Hp, Wp).
        """
        dn = self.pad_volume(delta_n)
        u = torch.fft.ifft2(self.source_spectrum(sources_um))
        for k in range(dn.shape[0]):
            if k:
                u = torch.fft.ifft2(torch.fft.fft2(u) * self._slice_kernel)
            u = u * phase_screen(dn[k], self.optics.slice_spacing_um, self.optics.wavelength_um)
        u = torch.fft.ifft2(torch.fft.fft2(u) * self._exit_kernel)
        return self.crop(u)

    def __call__(self, delta_n: torch.Tensor, sources_um: torch.Tensor, gain: torch.Tensor | None = None) -> torch.Tensor:
        """Images ``gain · |E|²``, (B, H, W) real; ``gain`` is (B,) or None (1)."""
        field = self.camera_field(delta_n, sources_um)
        intensity = field.real.square() + field.imag.square()
        if gain is not None:
            intensity = intensity * gain.to(self.device, self.dtype).reshape(-1, 1, 1)
        return intensity
