"""The multi-slice model on a window of the image and its light cone: the sources' field exact, the sample's on the window.

:class:`~napari_fdt.model.forward.MultiSliceModel` propagates each source's whole field on a periodic window that must
keep the source's periodic copies out of the light cone over the image: 7–16× the image's area on the suite
(``docs/physics.md``, "The window"). Most of that window carries only the source's field in the homogeneous
medium, which is known. :class:`SplitFieldModel` writes the field at every screen as ``E_k = U_k + S_k``:

* ``U_k``, the source's field in the homogeneous medium at screen k, is exact and non-periodic: a Hankel transform of
  the band-limited point source (:mod:`napari_fdt.physics.free_field`), tabulated in the radius once per step and
  interpolated at the pixels where the screens differ from 1 (the image). Its fast phase
  ``exp(i·2π·(n_b/λ)·(√(ρ² + H²) − H))`` is divided out before the table and multiplied back after, so the table's
  step can be 0.05 µm (relative error ~1e-4; linear interpolation of the raw profile needs 0.01 µm for 8e-4).
* ``S_k``, what the sample adds, starts at zero below the first screen and obeys
  ``S_{k+1} = P(S_k·t_k + (t_k − 1)·U_k)`` (P the propagator between screens, ``t_k`` the screen): it is born on the
  image, and what of it reaches the image through the pupil stays within the light cone's margin. It runs on the
  small periodic window (:func:`split_plan`: the image plus the margin ``T·tan θ_pupil`` and a clearance, per side).
* At the camera, ``U`` through the pupil is the exact homogeneous camera field (:mod:`napari_fdt.physics.free_field`,
  the same transform with the pupil), and ``S`` goes through the exit propagator and the pupil on the window.

Against the full-window model on a window 1.8× the plan's, where the copies are far (float64, the suite's truth volumes,
8 images each; ``docs/decisions/split-field.md``): image errors of 0.016–0.035 %, below the planned full window's
0.02–0.13 % (its copies' pupil tails) and far below the thin screen's own error (1–8 %). The FFTs run on 17–52 % of
the full window's pixels. Supported: one or more screens per slice, the pupil's edge, NA and aberrations (a
non-radial phase takes the camera's source field from the full window, one FFT per image), pixel integration,
per-call optics overrides (self-calibration, the spectral model), the per-source obliquity screens (each source's
screens scaled on the image by its rays' ``1/cos θ``: the screen update per source) and the 2× field grid
(:class:`~napari_fdt.model.oversampled.OversampledModel` with ``split``). A pupil edge narrower than the window's taper is
better served by the full window (its tails wrap on the small one): :func:`~napari_fdt.recon.problem.stages.uses_split_field`.
"""

from __future__ import annotations

import dataclasses
import math

import torch
import torch.nn.functional as F

from napari_fdt.model.forward import Kernels, MultiSliceModel, _has_nonradial, _value, secant_of_ray
from napari_fdt.physics.camera import fine_field, pixel_average_from_fine
from napari_fdt.physics.free_field import bessel_j0, free_field_profile, radial_nodes
from napari_fdt.physics.grid import GridPlan, next_fast_even
from napari_fdt.physics.optics import Optics
from napari_fdt.physics.propagation import phase_screen, phasor, pupil
from napari_fdt.physics.sources import band_limit

__all__ = ["SplitFieldModel", "split_plan", "CLEARANCE_UM", "TABLE_STEP_UM", "CAMERA_TABLE_STEP_UM"]

#: Clearance beyond the light cone's margin on each side of the image, µm. Measured (image error against the full
#: window, suite scenes): margins of about the cone's margin leave 0.01–0.04 %; 7 µm less, 0.15 %.
CLEARANCE_UM = 2.0
#: Radial steps of the demodulated profile tables, µm: the sources' field at the screens and their camera field. The
#: linear interpolation's error falls as the step squared; measured on the 32² test scene (sources 15–18 µm deep, NA
#: 0.8): screens 1.1e-4 at 0.1 µm, 2.8e-5 at 0.05; camera 1.1e-3 at 0.1, 2.7e-4 at 0.05, 1.1e-4 at 0.03.
TABLE_STEP_UM = 0.05
CAMERA_TABLE_STEP_UM = 0.02
#: The tables' quadrature panels end on the band's and the pupil's edges rounded to this, cycles/µm.
EDGE_ROUNDING = 1e-3
#: Oscillations of the integrand per 8-node Gauss–Legendre panel of the tables. Measured against 1/3 of an oscillation
#: per panel (float64, the sample's sources at every screen and at the camera): 1 leaves 4e-8 (screens) and 2e-7
#: (camera) of the field's largest value, 2 leaves 1.4e-7 and 1.4e-6, both far below the tables' interpolation
#: (1e-4) and float32's rounding (1e-4 here); the tables' matrix products cost half.
OSCILLATIONS_PER_PANEL = 2.0
#: Bessel tables a model keeps (oldest dropped first): a few node sets of the sources' and the camera's tables.
MAX_TABLES = 8
#: Fine pixels around the image where pixel integration adds the sources' camera field.
FINE_MARGIN = 32


def split_plan(plan: GridPlan, optics: Optics, clearance_um: float = CLEARANCE_UM) -> GridPlan:
    """The small window: the image plus ``margin_um + clearance_um`` per side (even 2·3·5-smooth sizes), never larger
    than ``plan``'s; the rest of ``plan`` (band limit, pupil taper) unchanged."""
    dx = optics.pixel_size_um
    reach = max(plan.margin_um, abs(optics.image_plane_um) * plan.margin_um / max(optics.thickness_um, 1e-9))
    pad = int(math.ceil((reach + clearance_um) / dx))
    shape = tuple(min(next_fast_even(n + 2 * pad), p) for n, p in zip(plan.image_shape, plan.padded_shape))
    h, w = plan.image_shape
    return dataclasses.replace(plan, padded_shape=shape, offset=(shape[0] // 2 - h // 2, shape[1] // 2 - w // 2))


class SplitFieldModel(MultiSliceModel):
    """:class:`~napari_fdt.model.forward.MultiSliceModel` with the sources' field exact and the sample's field on
    :func:`split_plan`'s window (see the module's docstring). ``plan`` is the full window's plan (from
    :func:`~napari_fdt.physics.grid.plan_grid`); the other keywords are :class:`MultiSliceModel`'s, except
    ``backward_mode`` (the loop runs on its written-out screens and propagators; accepted and ignored).
    The contrast volume must be on the image grid (n_slices, H, W).
    """

    def __init__(self, optics: Optics, plan: GridPlan, *, backward_mode: str = "auto", obliquity: str = "none",
                 exact_free_field: bool | str = "auto", clearance_um: float = CLEARANCE_UM, **options) -> None:
        self.full_plan = plan
        super().__init__(optics, split_plan(plan, optics, clearance_um), backward_mode="autograd", obliquity=obliquity,
                         exact_free_field=False, **options)
        self._tables: dict[tuple, torch.Tensor] = {}
        self._full: MultiSliceModel | None = None

    def pad_volume(self, delta_n: torch.Tensor) -> torch.Tensor:
        """The contrast on the image grid, (n_slices, H, W), on the model's device and dtype: the split model places it
        itself (callers that pad for the full-window model get it back unpadded)."""
        n = self.optics.n_slices
        h, w = self.plan.image_shape
        delta_n = delta_n.to(self.device, self.dtype)
        if tuple(delta_n.shape) != (n, h, w):
            raise ValueError(f"delta_n must have shape ({n}, {h}, {w}) (the image grid), got {tuple(delta_n.shape)}")
        return delta_n

    # -- the homogeneous fields ---------------------------------------------------------------
    def _profile_table(self, name: str, edges: list, amplitude_fn, depth: torch.Tensor, heights: torch.Tensor,
                       rho_max: float, lam, step: float) -> torch.Tensor:
        """Demodulated radial profiles (B·S, R) at radii ``r·step`` (µm) for source depths ``depth`` (B·S,) and
        source → plane distances ``heights`` (B·S,); ``amplitude_fn(f)`` the (real or complex) amplitude at the nodes.

        Gauss–Legendre panels of 8 nodes, one per :data:`OSCILLATIONS_PER_PANEL` oscillations of the integrand in f
        (``H·tan θ_max + ρ_max`` per cycle/µm: the phase ``2π·(q_z − n_b/λ)·H`` and the Bessel function's
        ``2π·f·ρ``); the Bessel table is kept per ``name`` while the nodes stay."""
        # the table's length and nodes in coarse buckets: the same for most batches (the Bessel table is reused, and an
        # image's field does not depend on the batch it is in: distributed runs match single-process ones)
        n_rho = 64 * int(math.ceil((rho_max / step + 3) / 64))
        s_max = min(0.999, _value(edges[-1]) * _value(lam) / self.optics.n_background)
        tan_max = s_max / math.sqrt(1.0 - s_max * s_max)
        reach = 12.8 * math.ceil(n_rho * step / 12.8)  # in 12.8 µm steps: the nodes change less often than the length
        rate = float(heights.detach().max()) * tan_max + reach + 4.0  # oscillations per cycle/µm, at most
        per_unit = 16.0 * math.ceil(rate / (16.0 * OSCILLATIONS_PER_PANEL))
        # The panels end on the edges rounded to EDGE_ROUNDING: fixed nodes while a fit of the pupil moves its NA and
        # edge a little each step (the Bessel table is kept; the gradient flows through the amplitude at the nodes:
        # the raised cosine's derivative is continuous, so a kink within the rounding of a panel's end costs O(h³))
        key = (tuple(round(_value(e) / EDGE_ROUNDING) * EDGE_ROUNDING for e in edges), per_unit)
        f, wts = radial_nodes(list(key[0]), per_unit, device=self.device, dtype=self.dtype)
        radii = torch.arange(n_rho, device=self.device, dtype=self.dtype) * step
        # a few tables per name: the training batch and the held-out images alternate, and may need different nodes
        cached = self._tables.get((name, key))
        if cached is not None and cached.shape[1] >= n_rho:
            bessel = cached[:, :n_rho]
        else:
            bessel = bessel_j0(2.0 * math.pi * f[:, None] * radii[None, :])
            if len(self._tables) >= MAX_TABLES:
                self._tables.pop(next(iter(self._tables)))
            self._tables[(name, key)] = bessel
        amp = amplitude_fn(f)
        if not amp.is_complex():
            amp = torch.complex(amp, torch.zeros_like(amp))
        prof = free_field_profile(radii, depth, heights, f, wts, amp, n_background=self.optics.n_background,
                                  wavelength_um=lam, bessel=bessel)
        return prof * _carrier(radii[None, :], heights[:, None], self.optics.n_background / lam, conj=True)

    def _evaluate(self, table: torch.Tensor, heights: torch.Tensor, rho: torch.Tensor, lam, step: float) -> torch.Tensor:
        """Profiles (B, S, R) from :meth:`_profile_table` (radial step ``step``) for sources (B,) at S planes (heights
        (B, S), µm) at each source's radii ``rho`` (B, P) → fields (B, S, P) (:class:`_Lookup`)."""
        k = torch.as_tensor(self.optics.n_background / lam, device=self.device, dtype=self.dtype)
        return _Lookup.apply(table, rho, heights, k, step)

    def incident_fields(self, sources_um: torch.Tensor, k: Kernels | None = None) -> torch.Tensor:
        """The sources' homogeneous-medium field at every screen on the image, (B, screens, H, W) complex: screen i at
        ``(i + 0.5)·step_um`` above the bottom face (the field envelope, as :meth:`MultiSliceModel.exit_spectra`'s)."""
        k = k or self._default
        oy, ox = self.plan.offset
        h, w = self.plan.image_shape
        ys = self._window_coordinates(oy, oy + h, 0, 1.0, k.pixel_size_um)
        xs = self._window_coordinates(ox, ox + w, 1, 1.0, k.pixel_size_um)
        rho = self.source_offsets(sources_um, ys, xs)[2]
        src = sources_um.to(self.device, self.dtype)
        heights = self._screen_heights(sources_um, k)
        b, n_screens = heights.shape
        depth = src[:, 2].reshape(-1, 1).expand(b, n_screens).reshape(-1)
        heights = heights.reshape(-1)
        ratio = self.optics.wavelength_um / k.wavelength_um
        f_lo, f_hi = self.plan.f_lo_per_um * ratio, self.plan.f_hi_per_um * ratio
        table = self._profile_table("incident", [0.0, f_lo, f_hi], lambda f: band_limit(f * f, f_lo, f_hi), depth,
                                    heights, float(rho.detach().max()), k.wavelength_um, TABLE_STEP_UM)
        out = self._evaluate(table.reshape(b, n_screens, -1), heights.reshape(b, n_screens), rho.reshape(b, h * w),
                             k.wavelength_um, TABLE_STEP_UM)
        return out.reshape(b, n_screens, h, w)

    def screen_secants(self, sources_um: torch.Tensor, k: Kernels | None = None) -> torch.Tensor:
        """``1/cos θ`` of each source's ray to every image pixel at every screen, (B, screens, H, W): the per-source
        obliquity screens' scale (``obliquity="per_source"``), :func:`~napari_fdt.model.forward.ray_secant`'s on the
        image (the contrast is zero beyond it), with its coordinates (the acquisition's pixel) and cap."""
        k = k or self._default
        oy, ox = self.plan.offset
        h, w = self.plan.image_shape
        dx = self.optics.pixel_size_um
        ys = self._window_coordinates(oy, oy + h, 0, 1.0, dx)
        xs = self._window_coordinates(ox, ox + w, 1, 1.0, dx)
        dy, dxs = self.source_offsets(sources_um, ys, xs)[:2]
        r2 = (dy * dy + dxs * dxs)[:, None]  # (B, 1, H, W)
        return secant_of_ray(self, r2, self._screen_heights(sources_um, k)[..., None, None])

    def _screen_heights(self, sources_um: torch.Tensor, k: Kernels) -> torch.Tensor:
        """Each source's distance below each screen, (B, screens) µm: its depth plus screen i's ``(i + 0.5)·step_um``
        above the bottom face."""
        n_screens = self.optics.n_slices * self.sub_slices
        z = (torch.arange(n_screens, device=self.device, dtype=self.dtype) + 0.5) * k.step_um
        return sources_um.to(self.device, self.dtype)[:, 2].reshape(-1, 1) + z.reshape(1, -1)

    def camera_free_field(self, sources_um: torch.Tensor, k: Kernels, ys: torch.Tensor, xs: torch.Tensor) -> torch.Tensor:
        """The sources' homogeneous-medium camera field (B, ny, nx) at window coordinates ``ys``, ``xs`` (µm), through
        the pupil of ``k``. A soft edge with rotationally symmetric aberrations: demodulated tables (exact, cheap); a
        hard edge: :meth:`MultiSliceModel.free_field_exact` (as the full-window model has it); a soft edge with other
        aberrations (a fit of them): the full window's periodic field (one FFT per image, as the full-window model)."""
        edge = k.pupil_edge
        hard = not isinstance(edge, torch.Tensor) and edge <= 0
        if hard:
            return self.free_field_exact(sources_um, k, ys, xs)
        if _has_nonradial(k.zernike):
            return self._periodic_free_field(sources_um, k, ys, xs)
        from napari_fdt.physics.aberrations import RADIAL_MODES, ZERNIKE_MODES, zernike_phase

        o = self.optics
        src = sources_um.to(self.device, self.dtype)
        lam = k.wavelength_um
        cutoff = k.na / lam
        edges = [0.0, (1.0 - edge) * cutoff, (1.0 + edge) * cutoff]
        heights = src[:, 2] + o.n_slices * k.slice_spacing_um - o.image_plane_um  # source → focal plane
        rho = self.source_offsets(sources_um, ys, xs)[2]
        amplitude = lambda f: pupil(f * f, k.na, lam, edge)  # noqa: E731
        if k.zernike is not None:  # radial modes only: a phase on the pupil
            keep = [ZERNIKE_MODES.index(m) for m in RADIAL_MODES]
            coeffs = torch.stack([k.zernike[i] for i in keep])

            def amplitude(f):
                w_r = zernike_phase(torch.zeros_like(f), f, o.na, o.wavelength_um, coeffs, RADIAL_MODES)
                return pupil(f * f, k.na, lam, edge) * phasor(w_r)

        table = self._profile_table("camera", edges, amplitude, src[:, 2], heights, float(rho.detach().max()), lam,
                                    CAMERA_TABLE_STEP_UM)
        b = rho.shape[0]
        out = self._evaluate(table.reshape(b, 1, -1), heights.reshape(b, 1), rho.reshape(b, -1), lam, CAMERA_TABLE_STEP_UM)
        return out.reshape(rho.shape)

    def _periodic_free_field(self, sources_um: torch.Tensor, k: Kernels, ys: torch.Tensor, xs: torch.Tensor) -> torch.Tensor:
        """The camera field of the sources alone on the full window (periodic; its copies kept off the image by the
        full plan), sampled at ``ys``, ``xs``: every pupil phase, at one FFT per image."""
        if self._full is None:
            self._full = MultiSliceModel(self.optics, self.full_plan, device=self.device, dtype=self.dtype,
                                         pupil_edge=self.pupil_edge, exact_free_field=True, backward_mode="autograd")
        kf = self._full.kernels(pixel_size_um=k.pixel_size_um, slice_spacing_um=k.slice_spacing_um,
                                wavelength_um=k.wavelength_um, na=k.na, pupil_edge=k.pupil_edge, zernike=k.zernike)
        field = torch.fft.ifft2(self._full.source_spectrum(sources_um, kf) * kf.free_kernel)
        # window coordinates (µm, from the centre) → full-window pixels; both windows are centred on the image
        hp, wp = self.full_plan.padded_shape
        rows = torch.round(ys.detach() / _value(k.pixel_size_um)).long() + hp // 2
        cols = torch.round(xs.detach() / _value(k.pixel_size_um)).long() + wp // 2
        if float(ys.detach()[1] - ys.detach()[0]) < 0.99 * _value(k.pixel_size_um):  # a finer grid: spectral zoom
            from napari_fdt.physics.camera import fine_field as _fine

            fine = _fine(torch.fft.fft2(field))
            rows = torch.round(2 * ys.detach() / _value(k.pixel_size_um)).long() + hp
            cols = torch.round(2 * xs.detach() / _value(k.pixel_size_um)).long() + wp
            return fine[:, rows][:, :, cols]
        return field[:, rows][:, :, cols]

    # -- the loop and the camera --------------------------------------------------------------
    def exit_spectra(self, delta_n: torch.Tensor, sources_um: torch.Tensor, k: Kernels | None = None) -> tuple[torch.Tensor, None]:
        """(spectrum of the sample's field ``S`` after the last screen on the window (B, Hs, Ws), None).

        The sources' part is added at the camera (:meth:`camera_free_field`); see
        :meth:`MultiSliceModel.exit_spectra` for what the pair is used for."""
        k = k or self._default
        h, w = self.plan.image_shape
        delta_n = self.pad_volume(delta_n)
        if not delta_n.requires_grad and not bool(delta_n.any()):  # t ≡ 1: the sample adds nothing (S ≡ 0)
            z = torch.zeros((sources_um.shape[0], *self.plan.padded_shape), device=self.device, dtype=self.dtype)
            return torch.complex(z, z), None
        if self.sub_slices > 1:
            delta_n = delta_n.repeat_interleave(self.sub_slices, dim=0)
        hp, wp = self.plan.padded_shape
        oy, ox = self.plan.offset
        pad = (ox, wp - w - ox, oy, hp - h - oy)
        # t − 1 per screen (H, W), or per source and screen (B, H, W) with the obliquity screens, and the sources' field
        # per screen (B, H, W): unbound, so that each one's gradient is one stack at the end of the backward pass, not a
        # zero-filled copy of the whole stack per screen
        if self.obliquity == "per_source":
            contrast = (phase_screen(delta_n * self.screen_secants(sources_um, k), k.step_um, k.wavelength_um) - 1.0).unbind(1)
        else:
            contrast = (phase_screen(delta_n, k.step_um, k.wavelength_um) - 1.0).unbind(0)
        sources = self.incident_fields(sources_um, k).unbind(1)
        kernel = k.slice_kernel
        # a kernel with a gradient (a calibrated pixel, spacing or wavelength) goes through plain autograd
        step = (lambda s: torch.fft.ifft2(torch.fft.fft2(s) * kernel)) if kernel.requires_grad else _Propagator(kernel)
        s = None
        for i in range(len(contrast)):
            if s is None:  # below the first screen the field is the sources' alone
                s = F.pad(contrast[i] * sources[i], pad)
                continue
            s = _ScreenUpdate.apply(step(s), contrast[i], sources[i], oy, ox)
        return torch.fft.fft2(s), None

    def _field_from_spectra(self, spec: torch.Tensor, free, sources_um: torch.Tensor, k: Kernels) -> torch.Tensor:
        oy, ox = self.plan.offset
        h, w = self.plan.image_shape
        ys = self._window_coordinates(oy, oy + h, 0, 1.0, k.pixel_size_um)
        xs = self._window_coordinates(ox, ox + w, 1, 1.0, k.pixel_size_um)
        return self.crop(torch.fft.ifft2(spec)) + self.camera_free_field(sources_um, k, ys, xs)

    def _integrated(self, spec: torch.Tensor, free, sources_um: torch.Tensor, k: Kernels) -> torch.Tensor:
        """Pixel means: the fine field of ``S`` on the window plus the sources' exact camera field on the image and a
        margin of :data:`FINE_MARGIN` fine pixels (beyond, the box filter does not reach the image)."""
        hp, wp = self.plan.padded_shape
        oy, ox = self.plan.offset
        h, w = self.plan.image_shape
        m = FINE_MARGIN
        r0, r1 = max(0, 2 * oy - m), min(2 * hp, 2 * (oy + h) + m)
        c0, c1 = max(0, 2 * ox - m), min(2 * wp, 2 * (ox + w) + m)
        ys = self._window_coordinates(r0, r1, 0, 0.5, k.pixel_size_um)
        xs = self._window_coordinates(c0, c1, 1, 0.5, k.pixel_size_um)
        free = F.pad(self.camera_free_field(sources_um, k, ys, xs), (c0, 2 * wp - c1, r0, 2 * hp - r1))
        return self.crop(pixel_average_from_fine(fine_field(spec) + free))

    def free_field_correction(self, *args, **kwargs):  # pragma: no cover - guard
        raise NotImplementedError("the split-field model adds the exact homogeneous field itself")


def _distance_and_excess_path(rho: torch.Tensor, heights: torch.Tensor, scale=1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """``(√(ρ² + H²), scale·(√(ρ² + H²) − H))`` (µm; broadcast), the second written without the cancellation near the
    axis, ``scale`` applied to ``ρ²`` (the smaller array where ρ is shared by several planes)."""
    rho2 = rho * rho
    r = torch.sqrt(rho2 + heights * heights)
    return r, (scale * rho2) / (r + heights)


def _excess_path(rho: torch.Tensor, heights: torch.Tensor) -> torch.Tensor:
    """``√(ρ² + H²) − H`` (µm), written without the cancellation near the axis."""
    return _distance_and_excess_path(rho, heights)[1]


def _carrier(rho: torch.Tensor, heights: torch.Tensor, k_per_um, *, conj: bool = False) -> torch.Tensor:
    """``exp(±i·2π·k·(√(ρ² + H²) − H))``: the homogeneous field's fast phase (the envelope's carrier removed)."""
    phase = (2.0 * math.pi) * k_per_um * _excess_path(rho, heights)
    if conj:
        phase = -phase
    return phasor(phase)


class _Propagator:
    """``S ↦ F⁻¹(K·F(S))`` for a constant kernel ``K`` (H, W) complex: its adjoint is the same map with ``conj(K)``
    (formed once for all screens), each product in place on the transform's fresh output (:class:`_Propagate`)."""

    def __init__(self, kernel: torch.Tensor) -> None:
        self.kernel = kernel
        self.conj_kernel = kernel.conj().resolve_conj()

    def __call__(self, s: torch.Tensor) -> torch.Tensor:
        return _Propagate.apply(s, self)


class _Propagate(torch.autograd.Function):
    @staticmethod
    def forward(ctx, s, prop):
        ctx.prop = prop
        return torch.fft.ifft2(torch.fft.fft2(s).mul_(prop.kernel))

    @staticmethod
    def backward(ctx, grad):
        return torch.fft.ifft2(torch.fft.fft2(grad).mul_(ctx.prop.conj_kernel)), None


class _ScreenUpdate(torch.autograd.Function):
    """A screen on the sample's field: ``S ← S·t + (t − 1)·U = S + (t − 1)·(S + U)`` on the image, in place.

    Inputs: ``s`` (B, Hs, Ws) complex, the field on the window just below the screen (a fresh tensor that nothing
    else keeps: it is changed in place); ``c`` (H, W) complex, ``t − 1``, or (B, H, W): each source's own screen (the
    obliquity screens; its gradient then not summed over B); ``u`` (B, H, W) complex, the sources' field
    at the screen; ``oy``, ``ox`` the image's offset in the window. Only the image's pixels change, so the backward is
    written out on them (``∂L/∂S = g + conj(c)·g`` on the image, ``∂L/∂U = conj(c)·g``, ``∂L/∂c = Σ_B conj(S + U)·g``),
    where plain autograd through a crop and a zero padding would fill and copy the whole window twice per screen.
    """

    @staticmethod
    def forward(ctx, s, c, u, oy, ox):
        h, w = c.shape[-2:]
        total = s[..., oy : oy + h, ox : ox + w] + u  # S + U on the image
        s[..., oy : oy + h, ox : ox + w] += c * total
        ctx.mark_dirty(s)
        ctx.save_for_backward(c, total if ctx.needs_input_grad[1] else None)
        ctx.region = (oy, ox, h, w)
        return s

    @staticmethod
    def backward(ctx, grad):
        c, total = ctx.saved_tensors
        oy, ox, h, w = ctx.region
        g = grad[..., oy : oy + h, ox : ox + w]
        g_image = g * c.conj()
        grad_c = None
        if ctx.needs_input_grad[1]:
            grad_c = g * total.conj()
            if c.dim() < grad_c.dim():  # one screen for every source
                grad_c = grad_c.sum(0)
        grad_s = None
        if ctx.needs_input_grad[0]:
            grad_s = grad.clone()
            grad_s[..., oy : oy + h, ox : ox + w] += g_image
        return grad_s, grad_c, g_image if ctx.needs_input_grad[2] else None, None, None


class _Lookup(torch.autograd.Function):
    """``U = g(ρ)·exp(i·2π·k·(√(ρ² + H²) − H))``: ``g`` the linear interpolation of a demodulated radial table.

    Inputs: ``table`` (B, S, R) complex (radial step ``step`` µm), ``rho`` (B, P) radii of each source's points (µm),
    ``heights`` (B, S) the source → plane distances (µm), ``k`` (0-d) n_b/λ (cycles/µm). Output (B, S, P) complex.
    The interpolation's index and weights are formed once per source and shared by its S planes, its slopes gathered
    from the table's differences; the backward is written out (the table's gradient scattered to its two neighbours,
    ρ's through the slope and the phase, H's and k's through the phase) in the conjugate frame, where no product needs
    a conjugated copy, keeping 28 bytes per output point (complex64) instead of plain autograd's ~200.
    """

    @staticmethod
    def forward(ctx, table, rho, heights, k, step):
        b, s, n = table.shape
        x = rho / step
        i0 = torch.clamp(torch.floor(x), 0, n - 2)
        t = (x - i0).clamp_(0.0, 1.0)
        inside = (x >= 0) & (x <= n - 1)  # beyond the table the value is its last entry's (no slope)
        index = i0.long()[:, None, :].expand(b, s, -1)  # a view: saved at (B, 1, P)
        slope = torch.gather(torch.diff(table, dim=2), 2, index)  # the table's step across the interval (demodulated)
        interp = torch.gather(table, 2, index).addcmul_(slope, t[:, None, :].to(table.dtype))
        r, phase = _distance_and_excess_path(rho[:, None, :], heights[..., None], (2.0 * math.pi) * k)
        carrier = phasor(phase)  # exp(i·2π·k·(√(ρ² + H²) − H))
        ctx.step = step
        ctx.table_len = n
        ctx.save_for_backward(index, t, inside, slope, interp, carrier, rho, heights, r, k)
        return interp * carrier

    @staticmethod
    def backward(ctx, grad):
        index, t, inside, slope, interp, carrier, rho, heights, r, k = ctx.saved_tensors
        grad_table = grad_rho = grad_h = grad_k = None
        h = grad.conj() * carrier  # conj(∂L/∂(interpolated value)): the demodulated frame, conjugated
        if ctx.needs_input_grad[0]:
            # each point's share at its lower neighbour less its t-weighted share, plus that at the upper neighbour:
            # two scatters on one index
            b, s = index.shape[:2]
            lower = torch.zeros((b, s, ctx.table_len), dtype=h.dtype, device=h.device).scatter_add_(2, index, h)
            share = torch.zeros_like(lower).scatter_add_(2, index, h * t[:, None, :])
            lower.sub_(share)[..., 1:].add_(share[..., :-1])
            grad_table = lower.conj()
        if not any(ctx.needs_input_grad[1:4]):
            return grad_table, None, None, None, None
        # the phase φ: dU/dφ = i·U, so ∂L/∂φ = Re(grad·conj(i·U)) = Im(grad·conj(U)) = −Im(h·interp)
        grad_phase = torch.imag(h * interp).neg_()
        two_pi_k = 2.0 * math.pi * k
        # dφ/dρ = 2πk·ρ/r, dφ/dH = 2πk·(H/r − 1): q = ∂L/∂φ · 2πk/r, summed over the planes or the points
        q = grad_phase / r
        if ctx.needs_input_grad[1]:
            along = torch.real(h * slope).sum(1) * (inside / ctx.step)  # the interpolation's slope
            grad_rho = along + two_pi_k * rho * q.sum(1)
        phase_sum = grad_phase.sum(-1)
        if ctx.needs_input_grad[2]:
            grad_h = two_pi_k * (heights * q.sum(-1) - phase_sum)
        if ctx.needs_input_grad[3]:  # Σ ∂L/∂φ·(r − H)·2π
            grad_k = (torch.dot(grad_phase.reshape(-1), r.reshape(-1)) - (heights * phase_sum).sum()) * (2.0 * math.pi)
        return grad_table, grad_rho, grad_h, grad_k, None
