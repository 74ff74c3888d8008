"""A cheap coarse forward model: envelopes of the spherical waves, propagated in angular coordinates.

The field of source i is written ``u = s·a`` with ``s = d·exp(ikR)/R`` its spherical wave and ``a`` an
envelope that the sample modulates. In the angular coordinate ``p = (x − x_i)/h`` (h the height above
the source) rays from the source are straight lines of constant p, and the Fresnel scaling theorem turns
the paraxial propagation of ``s·a`` over Δz between heights h and h + Δz into a plain Fresnel step of
the envelope,

    â(f_p) ← â(f_p) · exp(−iπ·λ'·f_p²·Δz / (h·(h + Δz))),       λ' = λ/n_b,

with f_p the frequency conjugate to p. The envelope is smooth wherever the RI is, so it can be sampled
at the *stage's* pixel: this model costs about (stage grid)² per image and slice instead of the full
window's, which makes early coarse-to-fine stages cheap. Screens are the same thin phase screens as in
the multi-slice model, sampled at ``x = x_i + p·h_k`` (bilinear, differentiable in the RI and the source
position); the pupil becomes an angular aperture ``|sin θ| ≤ NA/n_b`` (same soft edge), and the camera
sees ``gain·d²/(h_c²·(1 + |p|²))·|a|²``. The p-grid of each source is aligned so that camera pixel
(r, c) is p-grid point (r + o, c + o): no resampling at the camera.

Approximations, on top of the multi-slice model's: paraxial diffraction of the envelope about each
source's axis (exact transport along rays), and the pupil as an angular aperture (its edge diffraction
is not modelled; compare images only inside ``coverage``). It is meant for coarse stages; the final
stage uses :class:`~napari_fdt.model.forward.MultiSliceModel`.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from napari_fdt.model.envelope_loop import envelope_loop, step_kernels
from napari_fdt.physics.grid import next_fast_even
from napari_fdt.physics.optics import Optics
from napari_fdt.physics.propagation import axial_frequency_offset, phasor, pupil

__all__ = ["EnvelopeModel", "padding_px", "envelope_window"]


def padding_px(optics: Optics, factor: int) -> int:
    """Pixels of the stage grid (``factor · dx``) the envelope model pads each side with: envelope diffraction spreads by
    at most λ'/(2·pixel) over the thickness plus the exit distance, plus 4."""
    pixel_um = optics.pixel_size_um * factor
    lam_medium = optics.wavelength_um / optics.n_background
    reach = (optics.thickness_um + abs(optics.image_plane_um)) * lam_medium / (2 * pixel_um)
    return int(math.ceil(reach / pixel_um)) + 4


def envelope_window(optics: Optics, grid_shape: tuple[int, int], factor: int) -> tuple[tuple[int, int], tuple[int, int]]:
    """The envelope model's FFT window for a stage grid ``grid_shape`` (h, w) of ``factor``: ((hp, wp), (py, px)), the
    padded sides and the pixels before the grid on each axis. Each side is at least the grid plus
    :func:`padding_px` on both sides, rounded up to an even 2·3·5-smooth number (an FFT on 74 = 2·37 points costs 5×
    one on 80 on the CPU); the extra pixels go half before, half after the grid."""
    pad = padding_px(optics, factor)
    sides = tuple(next_fast_even(int(n) + 2 * pad) for n in grid_shape)
    lead = tuple((m - int(n)) // 2 for m, n in zip(sides, grid_shape))
    return sides, lead


class EnvelopeModel:
    """Coarse forward model on a stage grid (an :class:`~napari_fdt.model.protocol.ImageModel`).

    Parameters
    ----------
    optics: the acquisition's optics (the pixel size is the acquisition's; the stage pixel is
        ``factor × pixel_size_um``).
    grid_shape: (h, w) of the stage grid (RI and images).
    factor: stage factor.
    shift_um: (x, y) position of the stage grid's block-centre origin relative to the convention
        (see :mod:`napari_fdt.recon.problem.stages`).
    pupil_taper: soft edge of the angular aperture, as the pupil's.
    batched: ``True`` (default; ``"auto"`` is the same): all sources and slices in one batch (:meth:`images_batched`:
        few, large operations: ~3× fewer kernel launches on CUDA, and on a 2-core CPU the training step 1.5–1.6× faster
        on the suite scenes, 1.1–1.3× on the sample, measured 2026-11-26, ``docs/decisions/coarse-stage-models.md``);
        ``False``: one slice at a time (:meth:`images_per_slice`: many small operations, the reference). Same images and
        gradients (to rounding).
    """

    def __init__(self, optics: Optics, grid_shape: tuple[int, int], factor: int, shift_um: tuple[float, float],
                 *, pupil_taper: float = 0.03, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32,
                 batched: bool | str = True) -> None:
        self.optics = optics
        self.grid_shape = tuple(int(s) for s in grid_shape)
        self.factor = int(factor)
        self.pixel_um = optics.pixel_size_um * factor
        self.shift_um = shift_um
        self.pupil_taper = pupil_taper
        self.device = torch.device(device)
        self.dtype = dtype
        if batched not in (True, False, "auto"):
            raise ValueError(f"batched must be True, False or 'auto', got {batched!r}")
        self.batched = batched in (True, "auto")
        h, w = self.grid_shape
        self.padded, self.lead = envelope_window(optics, self.grid_shape, self.factor)

    @property
    def image_shape(self) -> tuple[int, int]:
        """(h, w) of the stage grid: the images this model returns."""
        return self.grid_shape

    @property
    def pixel_size_um(self) -> float:
        """Stage pixel, µm."""
        return self.pixel_um

    def _index(self, n: int) -> torch.Tensor:
        return torch.arange(n, device=self.device, dtype=self.dtype) - n // 2

    def coverage(self, sources_um: torch.Tensor, fraction: float = 0.9) -> torch.Tensor:
        """(B, h, w) 0/1: pixels seen at angles with sin θ below ``fraction``·NA/n_b (away from the aperture edge)."""
        with torch.no_grad():
            p2 = self._p2(sources_um.to(self.device, self.dtype))
            s2 = p2 / (1 + p2)
            lim = (fraction * self.optics.na / self.optics.n_background) ** 2
            return self._crop((s2 <= lim).to(self.dtype))

    def _p_axes(self, src: torch.Tensor):
        o = self.optics
        h_cam = src[:, 2] + o.thickness_um - o.image_plane_um  # (B,)
        dp = self.pixel_um / h_cam
        hp, wp = self.padded
        # camera pixel c ↔ p index c + lead; camera pixel c sits at x = (c − w//2)·D + shift_x
        jy = self._index(hp) + (hp // 2 - self.lead[0] - self.grid_shape[0] // 2)
        jx = self._index(wp) + (wp // 2 - self.lead[1] - self.grid_shape[1] // 2)
        py = ((jy[None] * self.pixel_um + self.shift_um[1]) - src[:, 1:2]) / h_cam[:, None]  # (B, hp)
        px = ((jx[None] * self.pixel_um + self.shift_um[0]) - src[:, 0:1]) / h_cam[:, None]  # (B, wp)
        return h_cam, dp, py, px

    def _p2(self, src: torch.Tensor) -> torch.Tensor:
        _, _, py, px = self._p_axes(src)
        return py[:, :, None] ** 2 + px[:, None, :] ** 2

    def _crop(self, a: torch.Tensor) -> torch.Tensor:
        h, w = self.grid_shape
        py, px = self.lead
        return a[..., py : py + h, px : px + w]

    @staticmethod
    def _kernel(f2p: torch.Tensor, h0: torch.Tensor, h1: torch.Tensor, n_background: float,
                wavelength_um: float | torch.Tensor) -> torch.Tensor:
        """Envelope step from height h0 to h1 (per source, (B,) µm): the Fresnel-scaled angular-spectrum kernel.

        In the frame of the scaling theorem the envelope at h0 propagates over ``Δz·h0/h1`` with physical
        frequency ``f = f_p/h0``; the exact kernel ``exp(i2π·Δz_eff·(q_z(f) − n_b/λ))`` replaces the paraxial
        ``exp(−iπ·λ'·f_p²·Δz/(h0·h1))`` (equal to leading order), evanescent frequencies set to 0.
        ``f2p``: (B, hp, wp) squared frequencies conjugate to p; returns (B, hp, wp) complex.
        """
        f2 = f2p / (h0 * h0)[:, None, None]
        dz_eff = ((h1 - h0) * h0 / h1)[:, None, None]
        offset, prop = axial_frequency_offset(f2, n_background, wavelength_um)
        return phasor(2 * math.pi * dz_eff * offset, prop.to(f2.dtype))

    def _heights(self, depth: torch.Tensor, dz, h_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(n, B) heights of the screens above each source, and (n, B) the height each step ends at (next screen; camera)."""
        n = self.optics.n_slices
        k = torch.arange(n, device=self.device, dtype=self.dtype) + 0.5
        heights = depth[None, :] + k[:, None] * dz
        ends = torch.cat([heights[1:], h_cam[None, :]], dim=0)
        return heights, ends

    def _screens(self, dn: torch.Tensor, src: torch.Tensor, px: torch.Tensor, py: torch.Tensor,
                 heights: torch.Tensor, k0dz) -> torch.Tensor:
        """Phases (radians) of the screens of every slice and source, (n, B, hp, wp) real, in one bilinear sampling.

        The p-grid of source b at height h sits at ``x = x_b + p·h``; each (slice, source) pair is one item of a
        single ``grid_sample`` call over the volume repeated per source (an (n·B, 1, h, w) copy of the stage grid).
        """
        n, b = heights.shape
        h, w = self.grid_shape
        hp, wp = self.padded
        xs = src[None, :, 0:1] + px[None, :, :] * heights[:, :, None]  # (n, B, wp)
        ys = src[None, :, 1:2] + py[None, :, :] * heights[:, :, None]  # (n, B, hp)
        u = (2 * ((xs - self.shift_um[0]) / self.pixel_um + w // 2) + 1) / w - 1
        v = (2 * ((ys - self.shift_um[1]) / self.pixel_um + h // 2) + 1) / h - 1
        grid = torch.stack(torch.broadcast_tensors(u[:, :, None, :], v[:, :, :, None]), dim=-1)  # (n, B, hp, wp, 2)
        vol = dn[:, None].expand(-1, b, -1, -1).reshape(n * b, 1, h, w)
        sample = F.grid_sample(vol, grid.reshape(n * b, hp, wp, 2), mode="bilinear", padding_mode="zeros",
                               align_corners=False).reshape(n, b, hp, wp)
        return k0dz * sample

    def __call__(self, delta_n: torch.Tensor, sources_um: torch.Tensor, gain: torch.Tensor | None = None,
                 *, slice_spacing_um=None, wavelength_um=None) -> torch.Tensor:
        """Images (B, h, w) on the stage grid for Δn (n_slices, h, w) on the stage grid; sources (B, 3) µm, gain (B,)."""
        run = self.images_batched if self.batched else self.images_per_slice
        return run(delta_n, sources_um, gain, slice_spacing_um=slice_spacing_um, wavelength_um=wavelength_um)

    def images_batched(self, delta_n: torch.Tensor, sources_um: torch.Tensor, gain: torch.Tensor | None = None,
                       *, slice_spacing_um=None, wavelength_um=None) -> torch.Tensor:
        """The images of :meth:`__call__`, every source and slice in one batch.

        Every source and slice is handled by the same few batched operations: one ``grid_sample`` for all screens,
        one kernel computation for all steps, then :func:`~napari_fdt.model.envelope_loop.envelope_loop` (4 operations
        per slice forward, 6 backward, with a hand-written adjoint) instead of ~30 per slice under plain autograd: on a
        GPU the coarse stage is less bound by kernel launches (counts: ``benchmarks/coarse_stage_speed.py``).
        """
        o = self.optics
        dz = o.slice_spacing_um if slice_spacing_um is None else slice_spacing_um
        lam = o.wavelength_um if wavelength_um is None else wavelength_um
        src = sources_um.to(self.device, self.dtype)
        dn = delta_n.to(self.device, self.dtype)
        hp, wp = self.padded
        h_cam, dp, py, px = self._p_axes(src)
        depth = src[:, 2]
        heights, ends = self._heights(depth, dz, h_cam)
        phases = self._screens(dn, src, px, py, heights, 2 * math.pi / lam * dz)
        # frequencies conjugate to p, per source: (1, B, hp, 1), (1, B, 1, wp); kernels of all steps: (n, B, hp, wp)
        fy = torch.fft.fftfreq(hp, device=self.device, dtype=self.dtype)[None, None, :, None] / dp[None, :, None, None]
        fx = torch.fft.fftfreq(wp, device=self.device, dtype=self.dtype)[None, None, None, :] / dp[None, :, None, None]
        f2p = fy * fy + fx * fx
        if isinstance(lam, torch.Tensor) and lam.requires_grad:  # differentiable wavelength: plain autograd
            kernels = self._kernels(f2p, heights, ends, o.n_background, lam) / (hp * wp)
        else:
            kernels = step_kernels(f2p, heights, ends, o.n_background, float(lam), 1.0 / (hp * wp))
        a = envelope_loop(phases, kernels)
        return self._camera(a, depth, h_cam, py, px, lam, gain)

    @staticmethod
    def _kernels(f2p: torch.Tensor, h0: torch.Tensor, h1: torch.Tensor, n_background: float,
                 wavelength_um: float | torch.Tensor) -> torch.Tensor:
        """:meth:`_kernel` for all steps at once (plain autograd): ``f2p`` (1, B, hp, wp), ``h0``, ``h1`` (n, B) → (n, B, hp, wp)."""
        f2 = f2p / (h0 * h0)[:, :, None, None]
        dz_eff = ((h1 - h0) * h0 / h1)[:, :, None, None]
        offset, prop = axial_frequency_offset(f2, n_background, wavelength_um)
        return phasor(2 * math.pi * dz_eff * offset, prop.to(f2.dtype))

    def _camera(self, a: torch.Tensor, depth: torch.Tensor, h_cam: torch.Tensor, py: torch.Tensor, px: torch.Tensor,
                lam, gain: torch.Tensor | None) -> torch.Tensor:
        """Camera images (B, h, w) from the envelopes (B, hp, wp) at the focal plane."""
        o = self.optics
        p2 = py[:, :, None] ** 2 + px[:, None, :] ** 2
        sin2 = p2 / (1 + p2)
        aperture = pupil(sin2 * (o.n_background / lam) ** 2, o.na, lam, self.pupil_taper)
        intensity = (depth**2 / h_cam**2)[:, None, None] / (1 + p2) * aperture**2 * (a.real.square() + a.imag.square())
        out = self._crop(intensity)
        if gain is not None:
            out = out * gain.to(self.device, self.dtype).reshape(-1, 1, 1)
        return out

    def images_per_slice(self, delta_n: torch.Tensor, sources_um: torch.Tensor, gain: torch.Tensor | None = None,
                         *, slice_spacing_um=None, wavelength_um=None) -> torch.Tensor:
        """The images of :meth:`__call__`, one slice at a time (~30 operations per slice, on (B, h, w) arrays).

        The first implementation, and the reference :meth:`images_batched` is tested against (``tests/test_envelope.py``).
        """
        o = self.optics
        dz = o.slice_spacing_um if slice_spacing_um is None else slice_spacing_um
        lam = o.wavelength_um if wavelength_um is None else wavelength_um
        src = sources_um.to(self.device, self.dtype)
        dn = delta_n.to(self.device, self.dtype)
        b = src.shape[0]
        h, w = self.grid_shape
        hp, wp = self.padded
        h_cam, dp, py, px = self._p_axes(src)
        depth = src[:, 2]
        fy = torch.fft.fftfreq(hp, device=self.device, dtype=self.dtype)[None, :, None] / dp[:, None, None]
        fx = torch.fft.fftfreq(wp, device=self.device, dtype=self.dtype)[None, None, :] / dp[:, None, None]
        f2 = fy * fy + fx * fx
        k0dz = 2 * math.pi / lam * dz
        a = None
        heights = [depth + (k + 0.5) * dz for k in range(o.n_slices)]
        vol = dn[None].expand(b, -1, -1, -1)  # (B, n, h, w), no copy
        for k, hk in enumerate(heights):
            xs = src[:, 0:1] + px * hk[:, None]  # (B, wp)
            ys = src[:, 1:2] + py * hk[:, None]  # (B, hp)
            u = (2 * ((xs - self.shift_um[0]) / self.pixel_um + w // 2) + 1) / w - 1
            v = (2 * ((ys - self.shift_um[1]) / self.pixel_um + h // 2) + 1) / h - 1
            grid = torch.stack(torch.broadcast_tensors(u[:, None, :], v[:, :, None]), dim=-1)  # (B, hp, wp, 2)
            sample = F.grid_sample(vol[:, k : k + 1], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[:, 0]
            screen = phasor(k0dz * sample)
            if a is None:
                a = screen
            else:
                a = torch.fft.ifft2(torch.fft.fft2(a) * self._kernel(f2, heights[k - 1], hk, o.n_background, lam)) * screen
        a = torch.fft.ifft2(torch.fft.fft2(a) * self._kernel(f2, heights[-1], h_cam, o.n_background, lam))
        return self._camera(a, depth, h_cam, py, px, lam, gain)
