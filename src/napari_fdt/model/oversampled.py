"""The multi-slice model with its field on a grid finer than the camera's and the RI's (issue 27, item 1).

On the camera grid (pixel ``dx``) the product of the field and a screen aliases above the grid's Nyquist frequency
``1/(2·dx)``: waves the sample scatters between there and the band the medium carries are folded back instead of
propagated (about 1.5–2 % of the images on the suite's beads at 0.33 µm pixels, NA 0.8; docs/physics.md, "A finer
field grid"). :class:`OversampledModel` runs the whole multi-slice model (sources, slices, pupil) on a grid ``2×``
finer over the same window in µm and returns images on the camera grid:

* **The RI on the fine grid.** The RI grid's values are samples of the sample's RI at the camera pixels' centres;
  fine pixel (2i, 2j) is coarse pixel (i, j), and the fine points between take the linear interpolation of their
  neighbours (zero contrast beyond the image: the background) (:func:`upsample_volume`).
* **The camera.** Point samples are the fine intensity at the even fine pixels; with ``pixel_integration`` the mean
  over each camera pixel is exact from the fine field (:func:`napari_fdt.physics.camera.pixel_average_from_fine`:
  the fine grid holds the intensity's whole band ``2·NA/λ`` whenever the camera grid holds the field's).

It costs about 4× a camera-grid model per slice (4× the pixels) and the fine volume's memory. The simulator uses it
with ``fdt simulate --field-oversampling 2`` (part of ``--forward-accuracy high``), the solver's finest stage with the
setting ``field_oversampling = 2`` (advanced; default 1, the camera grid).

``split=True`` runs the fine grid's field as :class:`~napari_fdt.model.split_field.SplitFieldModel` does the camera
grid's: the sources' field exact, the sample's on the image and its light cone (17–52 % of the full window's pixels);
the camera's point samples only (no ``pixel_integration``) and even image sizes (fine pixel 2i is camera pixel i).
"""

from __future__ import annotations

import dataclasses

import torch

from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.physics.camera import pixel_average_from_fine
from napari_fdt.physics.grid import GridPlan
from napari_fdt.physics.optics import Optics

__all__ = ["OversampledModel", "upsample_volume", "fine_plan", "fine_optics", "FACTOR"]

#: How much finer the field grid is than the camera's (per axis).
FACTOR = 2


def upsample_volume(delta_n: torch.Tensor) -> torch.Tensor:
    """(..., H, W) contrast on the camera grid → (..., 2H, 2W) on the fine field grid: fine (2i, 2j) = coarse (i, j),
    the points between the linear interpolation of their two (or four) neighbours, zero contrast beyond the last
    pixel (the background). Differentiable (linear)."""

    def along(x: torch.Tensor, dim: int) -> torch.Tensor:
        nxt = torch.cat([x.narrow(dim, 1, x.shape[dim] - 1), torch.zeros_like(x.narrow(dim, 0, 1))], dim=dim)
        both = torch.stack([x, 0.5 * (x + nxt)], dim=dim + 1 if dim >= 0 else dim)
        shape = list(x.shape)
        shape[dim] *= 2
        return both.reshape(shape)

    return along(along(delta_n, -1), -2)


def fine_optics(optics: Optics, factor: int = FACTOR) -> Optics:
    """``optics`` with the field grid's pixel, ``factor``× finer than the camera's."""
    return dataclasses.replace(optics, pixel_size_um=optics.pixel_size_um / factor)


def fine_plan(plan: GridPlan, factor: int = FACTOR) -> GridPlan:
    """The camera grid's plan on a grid ``factor``× finer over the same window (µm): fine window pixel ``factor·p`` is
    coarse window pixel ``p``, so the window's centre and every coarse pixel are fine pixels."""
    scale = lambda t: tuple(int(v) * factor for v in t)  # noqa: E731
    return dataclasses.replace(plan, image_shape=scale(plan.image_shape), padded_shape=scale(plan.padded_shape),
                               offset=scale(plan.offset), pixel_size_um=plan.pixel_size_um / factor)


class OversampledModel:
    """The multi-slice model on a field grid twice as fine as the camera's; images (B, H, W) on the camera grid.

    ``optics`` and ``plan`` are the camera's (as for :class:`~napari_fdt.model.forward.MultiSliceModel`); the other
    keywords go to the fine-grid :class:`~napari_fdt.model.forward.MultiSliceModel` (``pupil_edge``, ``aberrations``,
    ``sub_slices``, ``obliquity``, ...), except ``pixel_integration``, which this model applies at the camera.
    """

    def __init__(self, optics: Optics, plan: GridPlan, *, device: str | torch.device | None = "auto",
                 dtype: torch.dtype = torch.float32, pixel_integration: bool = False, split: bool = False,
                 **options) -> None:
        if any(s % 2 for s in plan.padded_shape):
            raise ValueError("the window must have even sizes")
        if split and (pixel_integration or any(s % 2 for s in plan.image_shape)):
            raise ValueError("the split fine grid takes point samples on an image of even sizes")
        self.optics = optics
        self.plan = plan
        self.factor = FACTOR
        self.pixel_integration = bool(pixel_integration)
        self.split = bool(split)
        if self.split:
            from napari_fdt.model.split_field import SplitFieldModel

            self.inner = SplitFieldModel(fine_optics(optics), fine_plan(plan), device=device, dtype=dtype, **options)
        else:
            self.inner = MultiSliceModel(fine_optics(optics), fine_plan(plan), device=device, dtype=dtype, **options)
        self.device, self.dtype = self.inner.device, self.inner.dtype

    # what the rest of the package reads of a model
    @property
    def image_shape(self) -> tuple[int, int]:
        """(H, W) of the images: the camera's."""
        return self.plan.image_shape

    @property
    def pixel_size_um(self) -> float:
        """The camera's pixel, µm (the field's is half of it)."""
        return self.optics.pixel_size_um

    @property
    def pupil_edge(self) -> float:
        return self.inner.pupil_edge

    @property
    def zernike(self) -> tuple[float, ...]:
        return self.inner.zernike

    @property
    def sub_slices(self) -> int:
        return self.inner.sub_slices

    def pad_volume(self, delta_n: torch.Tensor) -> torch.Tensor:
        """A (n, H, W) camera-grid contrast on the fine window, (n, 2Hp, 2Wp); a fine-window volume passes through."""
        delta_n = delta_n.to(self.device, self.dtype)
        if tuple(delta_n.shape[-2:]) == tuple(self.plan.image_shape):
            delta_n = upsample_volume(delta_n)
        return self.inner.pad_volume(delta_n)

    def _overrides(self, overrides: dict) -> dict:
        out = dict(overrides)
        if out.get("pixel_size_um") is not None:  # a calibrated camera pixel: the field's is half of it
            out["pixel_size_um"] = out["pixel_size_um"] / self.factor
        return out

    def kernels(self, **optics_overrides):
        """The fine-grid model's kernels (:meth:`MultiSliceModel.kernels`; a camera ``pixel_size_um`` is halved)."""
        return self.inner.kernels(**self._overrides(optics_overrides))

    def exit_spectra(self, delta_n: torch.Tensor, sources_um: torch.Tensor, k=None) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`MultiSliceModel.exit_spectra` on the fine grid (``delta_n`` on the camera grid or the fine window)."""
        return self.inner.exit_spectra(self.pad_volume(delta_n), sources_um, k)

    def intensity_from_exit(self, exit_spec: torch.Tensor, spec0: torch.Tensor, sources_um: torch.Tensor,
                            **optics_overrides) -> torch.Tensor:
        """:meth:`intensity` from :meth:`exit_spectra` (the pupil and camera applied here; see the camera-grid model's)."""
        k = self.kernels(**optics_overrides)
        if self.split:
            return self._split_camera(*self.inner._pupil_spectra(exit_spec, spec0, k), sources_um, k)
        return self._camera(self._field(*self.inner._pupil_spectra(exit_spec, spec0, k), sources_um, k))

    def fine_field(self, delta_n: torch.Tensor, sources_um: torch.Tensor, **optics_overrides) -> torch.Tensor:
        """The camera field on the whole fine window, (B, 2Hp, 2Wp) complex; exact (non-periodic) homogeneous part on
        the image and a margin where the model uses it (a pupil edge below the plan's taper). Not with ``split``."""
        if self.split:
            raise NotImplementedError("the split fine grid has the camera field on the image only (intensity)")
        k = self.kernels(**optics_overrides)
        spec, free = self.inner._camera_spectra(self.pad_volume(delta_n), sources_um, k)
        return self._field(spec, free, sources_um, k)

    def _field(self, spec: torch.Tensor, free: torch.Tensor | None, sources_um: torch.Tensor, k) -> torch.Tensor:
        field = torch.fft.ifft2(spec)
        if free is None:
            return field
        return field + self.inner.free_field_correction(torch.fft.ifft2(free), sources_um, k, 1)

    def intensity(self, delta_n: torch.Tensor, sources_um: torch.Tensor, **optics_overrides) -> torch.Tensor:
        """``|E|²`` on the camera's image, (B, H, W): at the pixel centres, or averaged over each pixel."""
        if self.split:
            k = self.kernels(**optics_overrides)
            return self._split_camera(*self.inner._camera_spectra(self.pad_volume(delta_n), sources_um, k), sources_um, k)
        return self._camera(self.fine_field(delta_n, sources_um, **optics_overrides))

    def _split_camera(self, spec: torch.Tensor, free: None, sources_um: torch.Tensor, k) -> torch.Tensor:
        """The split fine model's camera: ``|E|²`` at the even fine pixels of the image (the camera pixels' centres),
        the sample's field from its window and the sources' exact field there alone."""
        inner = self.inner
        oy, ox = inner.plan.offset
        h, w = inner.plan.image_shape
        sample = torch.fft.ifft2(spec)[..., oy:oy + h:2, ox:ox + w:2]
        ys = inner._window_coordinates(oy, oy + h, 0, 1.0, k.pixel_size_um)[::2]
        xs = inner._window_coordinates(ox, ox + w, 1, 1.0, k.pixel_size_um)[::2]
        field = sample + inner.camera_free_field(sources_um, k, ys, xs)
        return field.real.square() + field.imag.square()

    def _camera(self, field: torch.Tensor) -> torch.Tensor:
        if self.pixel_integration:
            camera = pixel_average_from_fine(field)
        else:
            coarse = field[..., ::2, ::2]
            camera = coarse.real.square() + coarse.imag.square()
        oy, ox = self.plan.offset
        h, w = self.plan.image_shape
        return camera[..., oy:oy + h, ox:ox + w]

    def __call__(self, delta_n: torch.Tensor, sources_um: torch.Tensor, gain: torch.Tensor | None = None,
                 **optics_overrides) -> torch.Tensor:
        """Images ``gain · |E|²`` on the camera grid, (B, H, W); ``delta_n`` (n, H, W) on the camera grid."""
        intensity = self.intensity(delta_n, sources_um, **optics_overrides)
        if gain is not None:
            intensity = intensity * gain.to(self.device, self.dtype).reshape(-1, 1, 1)
        return intensity
