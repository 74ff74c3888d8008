"""Differentiable multi-slice forward model: point sources → RI volume → camera images.

Geometry (``docs/physics.md``): light travels +z. Sources lie ``depth`` below the volume's bottom
face (z = 0); slice k (k = 0 nearest the sources) fills ``[k·Δz, (k+1)·Δz]`` and acts as a thin phase
screen at its middle (symmetric split step). The exit field at the top face z = T is
back-propagated by ``image_plane_um`` to the camera's focal plane, filtered by the pupil and
detected as ``gain · |E|²`` (optionally averaged over each camera pixel's area).

Optional parts (``docs/physics.md`` §3): the pupil's edge width and NA (``pupil_edge``, ``na``; 0 is a hard
edge), a Zernike pupil phase (``aberrations``), the exact non-periodic homogeneous field for pupils whose tails
the window cannot hold (``exact_free_field``) and pixel integration (``pixel_integration``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from napari_fdt.device import resolve_device
from napari_fdt.errors import FDTInputError
from napari_fdt.model.memory import grid_is_unitary
from napari_fdt.model.slice_loop import MODES, choose_mode, loop_forward, slice_loop
from napari_fdt.physics.aberrations import RADIAL_MODES, ZERNIKE_MODES, coefficients_vector, zernike_phase
from napari_fdt.physics.camera import fine_field, pixel_average_from_fine
from napari_fdt.physics.free_field import (
    DEFAULT_RHO_STEP_UM,
    MAX_HARMONIC,
    angular_harmonics,
    bessel_j0,
    bessel_orders,
    free_field_profile,
    interpolate_profile,
    radial_nodes,
)
from napari_fdt.physics.grid import GridPlan, frequency_grid
from napari_fdt.physics.optics import Optics
from napari_fdt.physics.propagation import phase_screen, phasor, propagation_kernel, pupil, screen_phase
from napari_fdt.physics.sources import band_limit, centering_sign, point_source_spectrum, spectrum_terms

__all__ = ["MultiSliceModel", "Kernels", "ray_secant"]


Scalar = float | torch.Tensor

#: Fine pixels around the image where the pixel-integrated intensity gets the exact homogeneous field (beyond, the
#: periodic one): keeps the jump between the two away from the box filter's reach.
FREE_FIELD_MARGIN = 16


@dataclass
class Kernels:
    """Everything the loop needs for one set of optical parameters (all on the model's device).

    ``fy``, ``fx``: frequencies (cycles/µm), (Hp, 1) and (1, Wp); ``window``: source band limit (Hp, Wp);
    ``slice_kernel``: propagation over one step between screens (a slice, or a sub-slice: ``step_um``); ``exit_kernel``:
    last screen → focal plane, times the
    pupil and its aberration phase; ``pixel_size_um``, ``slice_spacing_um``, ``wavelength_um``: the parameters they
    were built for; ``na``, ``pupil_edge``, ``zernike`` (coefficients of :data:`ZERNIKE_MODES`, radians) those of the
    pupil; ``free_kernel``: first screen → focal plane in the homogeneous medium, times the pupil and the radial
    aberrations (the periodic homogeneous field that the exact one replaces; None when not used).
    """

    fy: torch.Tensor
    fx: torch.Tensor
    window: torch.Tensor
    slice_kernel: torch.Tensor
    exit_kernel: torch.Tensor
    pixel_size_um: Scalar
    slice_spacing_um: Scalar
    wavelength_um: Scalar
    na: Scalar = 0.0
    pupil_edge: Scalar = 0.0
    zernike: torch.Tensor | None = None
    free_kernel: torch.Tensor | None = None
    #: the distance between screens, µm: ``slice_spacing_um / sub_slices`` (the slice spacing itself with one screen per slice)
    step_um: Scalar = 0.0


def _value(x: Scalar) -> float:
    """A number or a (possibly trained) scalar tensor as a float, outside autograd."""
    return float(x.detach()) if isinstance(x, torch.Tensor) else float(x)


def _has_nonradial(coeffs: torch.Tensor | None) -> bool:
    """Whether Zernike coefficients (of :data:`ZERNIKE_MODES`) include a non-rotationally-symmetric mode (or may: trained)."""
    if coeffs is None:
        return False
    if coeffs.requires_grad:
        return True
    idx = [i for i, m in enumerate(ZERNIKE_MODES) if m not in RADIAL_MODES]
    return bool((coeffs.detach()[idx] != 0).any())


class MultiSliceModel:
    """The forward model for one optics and grid plan (an :class:`~napari_fdt.model.protocol.ImageModel`).

    Parameters
    ----------
    optics: optics and sampling.
    plan: the window from :func:`napari_fdt.physics.grid.plan_grid`.
    device: ``"auto"``, ``"cpu"``, ``"cuda"`` or a torch device.
    dtype: real dtype, ``torch.float32`` (complex64 fields, default) or ``torch.float64``.
    backward_mode: how gradients of the slice loop are formed (:mod:`napari_fdt.model.slice_loop`):
        ``"auto"`` (default: ``"stored"`` when one field per slice and image fits in
        ``memory_budget_bytes``, else ``"reversible"`` for a unitary propagator, else ``"checkpoint"``),
        one of those three, or ``"autograd"`` (plain autograd through every operation: the reference).
    memory_budget_bytes: bytes the loop may keep in auto mode; None: 80 % of the device's free memory,
        read once per batch size.
    obliquity: ``"none"`` (default: thin screens, phase ``2π/λ·Δz·Δn`` for light of every direction) or
        ``"per_source"``: each source's screens scaled by ``1/cos θ`` of its ray to each voxel
        (:func:`ray_secant`), the path oblique light really travels in a slab. Removes
        the thin screen's obliquity error for the direct wave (2.4 % → 0.1 % image error at NA 0.66 under a
        uniform slab; ``docs/physics.md`` §6) at the cost of a screen per image and plain autograd (on the split
        window, :class:`~napari_fdt.model.split_field.SplitFieldModel`, a screen per image on the image alone).
    pupil_edge: half-width of the pupil's raised-cosine edge relative to NA/λ; 0: a hard pupil; None (default):
        the plan's ``pupil_taper`` (0.03, the edge the window is sized for).
    aberrations: ``{mode: radians}`` of :data:`napari_fdt.physics.aberrations.ZERNIKE_MODES` (None: none).
    exact_free_field: replace the periodic homogeneous part of each camera field by the exact non-periodic one
        (:mod:`napari_fdt.physics.free_field`), so that pupil tails beyond the window do not wrap; ``"auto"``
        (default): on when ``pupil_edge`` is narrower than the plan's ``pupil_taper``.
    pixel_integration: record the intensity averaged over each pixel's area instead of at its centre
        (:mod:`napari_fdt.physics.camera`).
    sub_slices: screens per slice (default 1): each slice of constant contrast is crossed in ``sub_slices`` symmetric
        steps (a screen of ``Δz/sub_slices`` at the centre of each sub-slice, propagation of ``Δz/sub_slices`` between),
        so that diffraction inside a thick slice is modelled; the thin screen's error falls as ``1/sub_slices²``
        (``docs/physics.md``, "Sub-slices"). Costs ``sub_slices`` times the slice loop.

    Call it as ``model(delta_n, sources_um, gain)`` → images (B, H, W). The optical parameters
    ``pixel_size_um``, ``slice_spacing_um`` and ``wavelength_um`` may be overridden per call, with
    floats or tensors (differentiable: self-calibration and the spectral-bandwidth model); kernels for
    the acquisition's own values are built once and cached.
    """

    def __init__(
        self,
        optics: Optics,
        plan: GridPlan,
        *,
        device: str | torch.device | None = "auto",
        dtype: torch.dtype = torch.float32,
        backward_mode: str = "auto",
        memory_budget_bytes: int | None = None,
        obliquity: str = "none",
        pupil_edge: float | None = None,
        aberrations: dict[str, float] | None = None,
        exact_free_field: bool | str = "auto",
        pixel_integration: bool = False,
        sub_slices: int = 1,
    ) -> None:
        if dtype not in (torch.float32, torch.float64):
            raise ValueError("dtype must be torch.float32 or torch.float64 (fp16 phases are too coarse)")
        if backward_mode not in ("auto", "autograd", *MODES):
            raise ValueError(f"backward_mode must be 'auto', 'autograd' or one of {MODES}, got {backward_mode!r}")
        if obliquity not in ("none", "per_source"):
            raise FDTInputError("obliquity", f"unknown correction {obliquity!r}", "use 'none' or 'per_source'")
        self.obliquity = obliquity
        self.pupil_edge = float(plan.pupil_taper if pupil_edge is None else pupil_edge)
        if not (0.0 <= self.pupil_edge < 0.5):
            raise FDTInputError("pupil_edge", f"must be in [0, 0.5), got {pupil_edge!r}", "0 is a hard pupil; 0.03 the default soft edge")
        self.zernike = tuple(coefficients_vector(aberrations))
        if exact_free_field == "auto":
            exact_free_field = self.pupil_edge < plan.pupil_taper
        self.exact_free_field = bool(exact_free_field)
        self.pixel_integration = bool(pixel_integration)
        if isinstance(sub_slices, bool) or int(sub_slices) != sub_slices or int(sub_slices) < 1:
            raise FDTInputError("sub_slices", f"must be a whole number >= 1, got {sub_slices!r}",
                                "1 (a thin screen per slice), or 2-4 for thick slices")
        self.sub_slices = int(sub_slices)
        self._bessel_cache: dict = {}
        self.backward_mode = backward_mode
        self.memory_budget_bytes = memory_budget_bytes
        self._auto_modes: dict[int, str] = {}
        # reversible needs |K| = 1 on the whole grid (grid_is_unitary leaves room for pixel-size calibration)
        self._unitary = grid_is_unitary(optics.pixel_size_um, optics.n_background, optics.wavelength_um)
        if backward_mode == "reversible" and not self._unitary:
            raise FDTInputError(
                "backward_mode", f"'reversible' needs a grid without evanescent frequencies; pixels of "
                f"{optics.pixel_size_um} µm at λ {optics.wavelength_um} µm, n_b {optics.n_background} have some",
                "use 'auto' or 'checkpoint' (or pixels of at least λ/(√2·n_b)·1.02)")
        self.optics = optics
        self.plan = plan
        self.device = resolve_device(device)
        self.dtype = dtype
        self._centering = centering_sign(plan.padded_shape, device=self.device, dtype=dtype)
        self._default = self.kernels()
        self._default_terms: tuple[torch.Tensor, torch.Tensor] | None = None  # source_spectrum's, made at first use

    @property
    def image_shape(self) -> tuple[int, int]:
        """(H, W) of the images this model returns."""
        return self.plan.image_shape

    @property
    def pixel_size_um(self) -> float:
        """Sampling of the images, µm."""
        return self.optics.pixel_size_um

    # -- kernels ------------------------------------------------------------------------------
    def kernels(
        self,
        pixel_size_um: Scalar | None = None,
        slice_spacing_um: Scalar | None = None,
        wavelength_um: Scalar | None = None,
        na: Scalar | None = None,
        pupil_edge: Scalar | None = None,
        zernike: torch.Tensor | None = None,
    ) -> Kernels:
        """Kernels for the given parameters (None: the acquisition's or the model's value); cached when all are None.

        A different wavelength scales the band limit and the pupil with it (they are angles); the Zernike
        polynomials' unit radius stays the acquisition's NA/λ.
        """
        overrides = (pixel_size_um, slice_spacing_um, wavelength_um, na, pupil_edge, zernike)
        if all(v is None for v in overrides) and hasattr(self, "_default"):
            return self._default
        o = self.optics
        dx = o.pixel_size_um if pixel_size_um is None else pixel_size_um
        dz = o.slice_spacing_um if slice_spacing_um is None else slice_spacing_um
        lam = o.wavelength_um if wavelength_um is None else wavelength_um
        fy, fx = frequency_grid(self.plan.padded_shape, 1.0, device=self.device, dtype=self.dtype)
        fy, fx = fy / dx, fx / dx
        f2 = fy * fy + fx * fx
        ratio = o.wavelength_um / lam  # band limits are angles: frequencies scale as 1/λ
        window = band_limit(f2, self.plan.f_lo_per_um * ratio, self.plan.f_hi_per_um * ratio)
        step = dz / self.sub_slices  # between screens: a slice, or one of its sub-slices
        slice_kernel = propagation_kernel(f2, step, o.n_background, lam)
        exit_distance = 0.5 * step - o.image_plane_um  # last screen → camera focal plane
        na_ = o.na if na is None else na
        edge = self.pupil_edge if pupil_edge is None else pupil_edge
        coeffs = zernike
        if coeffs is None and any(self.zernike):
            coeffs = torch.tensor(self.zernike, device=self.device, dtype=self.dtype)
        aperture = pupil(f2, na_, lam, edge).to(torch.complex128 if self.dtype == torch.float64 else torch.complex64)
        radial = aperture
        if coeffs is not None:
            phase_all = zernike_phase(fy, fx, o.na, o.wavelength_um, coeffs)
            aperture = aperture * phasor(phase_all)
            keep = [ZERNIKE_MODES.index(m) for m in RADIAL_MODES]
            radial_coeffs = torch.stack([coeffs[i] for i in keep])
            phase_r = zernike_phase(fy, fx, o.na, o.wavelength_um, radial_coeffs, RADIAL_MODES)
            radial = radial * phasor(phase_r)
        exit_kernel = propagation_kernel(f2, exit_distance, o.n_background, lam) * aperture
        free_kernel = None
        if self.exact_free_field:
            free_distance = o.n_slices * dz - 0.5 * step - o.image_plane_um  # first screen → focal plane
            full = _has_nonradial(coeffs)  # the exact field then holds every mode (angular harmonics)
            free_kernel = propagation_kernel(f2, free_distance, o.n_background, lam) * (aperture if full else radial)
        return Kernels(fy, fx, window, slice_kernel, exit_kernel, dx, dz, lam, na_, edge, coeffs, free_kernel, step)

    # -- pieces -------------------------------------------------------------------------------
    def source_spectrum(self, sources_um: torch.Tensor, kernels: Kernels | None = None) -> torch.Tensor:
        """(B, Hp, Wp) spectrum of the sources at the first screen (half a step above the bottom face).

        With the model's own kernels (no optics override) the factors that do not depend on the sources are made once.
        """
        k = kernels or self._default
        terms = None
        if k is self._default:
            if self._default_terms is None:
                self._default_terms = spectrum_terms(k.fy, k.fx, n_background=self.optics.n_background,
                                                     wavelength_um=k.wavelength_um, pixel_size_um=k.pixel_size_um,
                                                     window=k.window, centering=self._centering)
            terms = self._default_terms
        return point_source_spectrum(
            k.fy,
            k.fx,
            sources_um.to(self.device, self.dtype),
            0.5 * k.step_um,
            n_background=self.optics.n_background,
            wavelength_um=k.wavelength_um,
            pixel_size_um=k.pixel_size_um,
            window=k.window,
            centering=self._centering,
            terms=terms,
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

    def _camera_spectra(self, delta_n: torch.Tensor, sources_um: torch.Tensor, k: Kernels) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Spectra (B, Hp, Wp) of the camera field on the window and of its periodic homogeneous part (None if unused)."""
        return self._pupil_spectra(*self.exit_spectra(delta_n, sources_um, k), k)

    def exit_spectra(self, delta_n: torch.Tensor, sources_um: torch.Tensor, k: Kernels | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(spectrum of the field after the last screen, spectrum of the sources at the first screen), each (B, Hp, Wp).

        Everything of the image that does not depend on the pupil (its NA, edge and aberrations) or the camera: a
        fit of those with the volume and sources held fixed computes these once and calls :meth:`intensity_from_exit`.
        """
        k = k or self._default
        dn = self.pad_volume(delta_n)
        if self.sub_slices > 1:  # each slice's contrast on each of its sub-slices
            dn = dn.repeat_interleave(self.sub_slices, dim=0)
        spec0 = self.source_spectrum(sources_um, k)
        v0 = torch.fft.ifft2(spec0)
        if self.obliquity == "per_source" or self.backward_mode == "autograd":  # plain autograd
            src = sources_um.to(self.device, self.dtype)
            u = v0
            for i in range(dn.shape[0]):
                if i:
                    u = torch.fft.ifft2(torch.fft.fft2(u) * k.slice_kernel)
                dn_i = dn[i] if self.obliquity == "none" else dn[i] * ray_secant(self, src, (i + 0.5) * k.step_um)
                u = u * phase_screen(dn_i, k.step_um, k.wavelength_um)
        else:
            phi = screen_phase(dn, k.step_um, k.wavelength_um)
            if torch.is_grad_enabled() and (v0.requires_grad or phi.requires_grad or k.slice_kernel.requires_grad):
                u = slice_loop(v0, phi, k.slice_kernel, self.loop_mode(v0.shape[0]), check=False)
            else:  # inference: nothing to keep
                u = loop_forward(v0, phi, k.slice_kernel)
        return torch.fft.fft2(u), spec0

    @staticmethod
    def _pupil_spectra(exit_spec: torch.Tensor, spec0: torch.Tensor, k: Kernels) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Camera-field spectrum (exit spectrum through the exit kernel) and its periodic homogeneous part (or None)."""
        return exit_spec * k.exit_kernel, (None if k.free_kernel is None else spec0 * k.free_kernel)

    def _window_coordinates(self, start: int, stop: int, axis: int, step: float, dx: Scalar) -> torch.Tensor:
        """Lateral coordinates (µm) of window positions ``start·step … (stop−1)·step`` along rows (0) or columns (1)."""
        n = self.plan.padded_shape[axis]
        idx = torch.arange(start, stop, device=self.device, dtype=self.dtype) * step
        return (idx - n // 2) * dx

    def source_offsets(self, sources_um: torch.Tensor, ys: torch.Tensor, xs: torch.Tensor):
        """``(dy, dx, ρ)`` of window coordinates ``ys`` (ny,), ``xs`` (nx,) µm from each source: (B, ny, 1), (B, 1, nx) and
        (B, ny, nx) µm (ρ kept off 0, where its derivative is undefined)."""
        src = sources_um.to(self.device, self.dtype)
        dy = ys.reshape(1, -1, 1) - src[:, 1].reshape(-1, 1, 1)
        dx = xs.reshape(1, 1, -1) - src[:, 0].reshape(-1, 1, 1)
        return dy, dx, torch.sqrt(dy * dy + dx * dx + 1e-12)

    def free_field_exact(self, sources_um: torch.Tensor, k: Kernels, ys: torch.Tensor, xs: torch.Tensor) -> torch.Tensor:
        """Non-periodic homogeneous-medium camera field (B, ny, nx) at window coordinates ``ys`` (ny,), ``xs`` (nx,) µm.

        Through the pupil of ``k`` and its rotationally symmetric aberrations (:mod:`napari_fdt.physics.free_field`).
        """
        o = self.optics
        src = sources_um.to(self.device, self.dtype)
        lam = k.wavelength_um
        cutoff = k.na / lam
        edge = k.pupil_edge
        hard = not isinstance(edge, torch.Tensor) and edge <= 0
        edges = [0.0, cutoff] if hard else [0.0, (1.0 - edge) * cutoff, (1.0 + edge) * cutoff]
        thickness = o.n_slices * k.slice_spacing_um
        h = src[:, 2] + thickness - o.image_plane_um  # source → focal plane
        dy, dxx, rho = self.source_offsets(sources_um, ys, xs)
        step = DEFAULT_RHO_STEP_UM
        rho_max = float(rho.detach().max()) + 2 * step
        n_rho = int(math.ceil(rho_max / step)) + 2
        f_max = _value(edges[-1])
        s_max = min(0.999, f_max * _value(lam) / o.n_background)
        tan_max = s_max / math.sqrt(1.0 - s_max * s_max)
        per_unit = 1.25 * (float(h.detach().max()) * tan_max + rho_max) + 4.0
        per_unit = 2.0 ** math.ceil(math.log2(per_unit))  # few distinct node sets: the Bessel table is reused
        f, wts = radial_nodes(edges, per_unit, device=self.device, dtype=self.dtype)
        radii = torch.arange(n_rho, device=self.device, dtype=self.dtype) * step
        amp = pupil(f * f, k.na, lam, edge)
        amp = torch.complex(amp, torch.zeros_like(amp))
        if not _has_nonradial(k.zernike):
            key = None
            if not f.requires_grad:
                key = (tuple(round(_value(e), 12) for e in edges), per_unit)
            bessel = self._bessel_cache.get(key) if key is not None else None
            if bessel is not None and bessel.shape[1] >= n_rho:  # radii are a prefix of the cached ones
                bessel = bessel[:, :n_rho]
            else:
                bessel = bessel_j0(2.0 * math.pi * f[:, None] * radii[None, :])
                if key is not None:
                    self._cache_bessel(key, bessel)
            if k.zernike is not None:
                keep = [ZERNIKE_MODES.index(m) for m in RADIAL_MODES]
                w_r = zernike_phase(torch.zeros_like(f), f, o.na, o.wavelength_um, torch.stack([k.zernike[i] for i in keep]), RADIAL_MODES)
                amp = amp * phasor(w_r)
            profile = free_field_profile(radii, src[:, 2], h, f, wts, amp, n_background=o.n_background, wavelength_um=lam, bessel=bessel)
            return interpolate_profile(profile, step, rho)
        # Angular harmonics: exp(i·W(f, φ)) = Σ_m c_m(f)·exp(i·m·φ) → E(ρ, θ) = Σ_m i^m·exp(i·m·θ)·2π∫A·c_m·J_m(2πfρ)·f df
        n_phi = 64
        ang = torch.arange(n_phi, device=self.device, dtype=self.dtype) * (2.0 * math.pi / n_phi)
        w_full = zernike_phase(f[:, None] * torch.sin(ang)[None, :], f[:, None] * torch.cos(ang)[None, :], o.na, o.wavelength_um, k.zernike)
        coeffs, order = angular_harmonics(phasor(w_full))  # (2M+1, F)
        cplx = torch.complex128 if self.dtype == torch.float64 else torch.complex64
        unit = torch.complex(dxx, dy) / rho  # exp(i·θ) of each pixel seen from its source
        unit = unit.expand(src.shape[0], -1, -1) if unit.shape[0] != src.shape[0] else unit
        # The J_m tables do not follow the nodes' motion with the NA and edge: those two gradients are approximate here
        # (4 % in d/dNA on a test case); the coefficients' gradients are exact.
        key = ("harmonics", tuple(round(_value(e), 12) for e in edges), per_unit)
        tables = self._bessel_cache.get(key)
        if tables is None or len(tables) <= order or tables[0][1].shape[1] < n_rho:
            # J_0 … J_M on (nodes × radii): the same while the pupil's edges stay (cached like J_0's); a few orders
            # beyond the one needed and 25 % more radii, so that a trained phase whose order grows by one, or a batch
            # of sources a little farther from the image, does not rebuild them (the radii are a prefix)
            n_keep = int(1.25 * n_rho) + 1
            wide = torch.arange(n_keep, device=self.device, dtype=self.dtype) * step
            z = 2.0 * math.pi * f.detach()[:, None] * wide[None, :]
            tables = [(m, jm.to(self.dtype)) for m, jm in bessel_orders(z, min(order + 2, MAX_HARMONIC))]
            self._cache_bessel(key, tables)
        out = None
        power = torch.ones_like(unit)
        for m, jm_all in tables[: order + 1]:
            jm = jm_all[:, :n_rho]
            for sign in ((1,) if m == 0 else (1, -1)):
                c_m = coeffs[order + sign * m]
                bes = jm if (sign > 0 or m % 2 == 0) else -jm  # J_{-m} = (−1)^m·J_m
                prof = free_field_profile(radii, src[:, 2], h, f, wts, amp * c_m, n_background=o.n_background,
                                          wavelength_um=lam, bessel=bes)
                phase_m = (1j) ** (sign * m)
                term = interpolate_profile(prof, step, rho) * (power if sign > 0 else power.conj()) * torch.tensor(phase_m, dtype=cplx)
                out = term if out is None else out + term
            power = power * unit
        return out

    def _cache_bessel(self, key: tuple, tables) -> None:
        """Keep Bessel tables for ``key``, with at most one other entry (the J₀ table and the harmonics' tables of one
        pupil both stay: training and validation may use either)."""
        while len(self._bessel_cache) >= 2:
            self._bessel_cache.pop(next(iter(self._bessel_cache)))
        self._bessel_cache[key] = tables

    def camera_field(
        self,
        delta_n: torch.Tensor,
        sources_um: torch.Tensor,
        **optics_overrides: Scalar | None,
    ) -> torch.Tensor:
        """Complex field at the camera, (B, H, W), for contrast ``delta_n = n − n_b`` (at the pixel centres).

        ``delta_n`` is (n_slices, H, W) on the image grid (background outside) or (n_slices, Hp, Wp).
        Keyword overrides: see :meth:`kernels`.
        """
        k = self.kernels(**optics_overrides)
        spec, free = self._camera_spectra(delta_n, sources_um, k)
        return self._field_from_spectra(spec, free, sources_um, k)

    def intensity(self, delta_n: torch.Tensor, sources_um: torch.Tensor, **optics_overrides: Scalar | None) -> torch.Tensor:
        """``|E|²`` on the image, (B, H, W): at the pixel centres, or averaged over each pixel with ``pixel_integration``."""
        if not self.pixel_integration:
            field = self.camera_field(delta_n, sources_um, **optics_overrides)
            return field.real.square() + field.imag.square()
        k = self.kernels(**optics_overrides)
        return self._integrated(*self._camera_spectra(delta_n, sources_um, k), sources_um, k)

    def intensity_from_exit(self, exit_spec: torch.Tensor, spec0: torch.Tensor, sources_um: torch.Tensor,
                            **optics_overrides: Scalar | None) -> torch.Tensor:
        """:meth:`intensity` from :meth:`exit_spectra`, which must have been computed for the same sources and with the
        same ``pixel_size_um``, ``slice_spacing_um`` and ``wavelength_um`` as given here; ``na``, ``pupil_edge`` and
        ``zernike`` may differ (the pupil is applied here)."""
        k = self.kernels(**optics_overrides)
        spec, free = self._pupil_spectra(exit_spec, spec0, k)
        if self.pixel_integration:
            return self._integrated(spec, free, sources_um, k)
        field = self._field_from_spectra(spec, free, sources_um, k)
        return field.real.square() + field.imag.square()

    def _field_from_spectra(self, spec: torch.Tensor, free: torch.Tensor | None, sources_um: torch.Tensor, k: Kernels) -> torch.Tensor:
        """The camera field (B, H, W) at the pixel centres from :meth:`_pupil_spectra`."""
        field = self.crop(torch.fft.ifft2(spec))
        if free is not None:
            oy, ox = self.plan.offset
            h, w = self.plan.image_shape
            ys = self._window_coordinates(oy, oy + h, 0, 1.0, k.pixel_size_um)
            xs = self._window_coordinates(ox, ox + w, 1, 1.0, k.pixel_size_um)
            field = field - self.crop(torch.fft.ifft2(free)) + self.free_field_exact(sources_um, k, ys, xs)
        return field

    def _integrated(self, spec: torch.Tensor, free: torch.Tensor | None, sources_um: torch.Tensor, k: Kernels) -> torch.Tensor:
        """Pixel-averaged intensity (B, H, W) from :meth:`_pupil_spectra`."""
        fine = fine_field(spec)
        if free is not None:  # exact homogeneous field on the image and a margin (the box filter's reach)
            fine = fine + self.free_field_correction(fine_field(free), sources_um, k, 2)
        return self.crop(pixel_average_from_fine(fine))

    def free_field_correction(self, periodic: torch.Tensor, sources_um: torch.Tensor, k: Kernels, scale: int) -> torch.Tensor:
        """Exact minus periodic homogeneous field, (B, scale·Hp, scale·Wp), on the image and a margin of
        :data:`FREE_FIELD_MARGIN` pixels of a grid ``scale``× finer than the window's, zero elsewhere; ``periodic``
        is the periodic homogeneous field on that grid."""
        oy, ox = self.plan.offset
        h, w = self.plan.image_shape
        hp, wp = self.plan.padded_shape
        m = FREE_FIELD_MARGIN
        r0, r1 = max(0, scale * oy - m), min(scale * hp, scale * (oy + h) + m)
        c0, c1 = max(0, scale * ox - m), min(scale * wp, scale * (ox + w) + m)
        ys = self._window_coordinates(r0, r1, 0, 1.0 / scale, k.pixel_size_um)
        xs = self._window_coordinates(c0, c1, 1, 1.0 / scale, k.pixel_size_um)
        corr = self.free_field_exact(sources_um, k, ys, xs) - periodic[..., r0:r1, c0:c1]
        return F.pad(corr, (c0, scale * wp - c1, r0, scale * hp - r1))

    def loop_mode(self, batch: int) -> str:
        """The backward mode used for a batch of ``batch`` images (see ``backward_mode``)."""
        if self.backward_mode != "auto":
            return self.backward_mode
        if batch not in self._auto_modes:
            budget = self.memory_budget_bytes
            if budget is None:
                from napari_fdt.device import available_bytes

                free = available_bytes(self.device)
                budget = None if free is None else int(0.8 * free)
            hp, wp = self.plan.padded_shape
            field_bytes = hp * wp * (8 if self.dtype == torch.float32 else 16)
            self._auto_modes[batch] = choose_mode(field_bytes, self.optics.n_slices * self.sub_slices, batch, self._unitary, budget)
        return self._auto_modes[batch]

    def __call__(
        self,
        delta_n: torch.Tensor,
        sources_um: torch.Tensor,
        gain: torch.Tensor | None = None,
        **optics_overrides: Scalar | None,
    ) -> torch.Tensor:
        """Images ``gain · |E|²``, (B, H, W) real; ``gain`` is (B,) or None (1).

        Keyword overrides: ``pixel_size_um``, ``slice_spacing_um``, ``wavelength_um``, ``na``, ``pupil_edge``,
        ``zernike`` (see :meth:`kernels`).
        """
        intensity = self.intensity(delta_n, sources_um, **optics_overrides)
        if gain is not None:
            intensity = intensity * gain.to(self.device, self.dtype).reshape(-1, 1, 1)
        return intensity


def ray_secant(model, sources_um: torch.Tensor, height_um: torch.Tensor | float, *, max_sine: float | None = None) -> torch.Tensor:
    """``1/cos θ`` of the ray from each source to every window pixel at ``height_um`` above the bottom face, (B, Hp, Wp).

    ``tan θ = r / (depth + height)``, r the lateral distance from the source (window coordinates, pixel (i, j) at
    ``((i − Hp/2)·dx, (j − Wp/2)·dx)``); capped at the band limit's angle (``max_sine``, default the plan's f_hi).
    """
    hp, wp = model.plan.padded_shape
    dx = model.pixel_size_um
    dev, dt = model.device, model.dtype
    y = ((torch.arange(hp, device=dev, dtype=dt) - hp // 2) * dx).reshape(1, hp, 1)
    x = ((torch.arange(wp, device=dev, dtype=dt) - wp // 2) * dx).reshape(1, 1, wp)
    src = sources_um.to(dev, dt)
    h = (src[:, 2] + height_um).reshape(-1, 1, 1)
    r2 = (x - src[:, 0].reshape(-1, 1, 1)) ** 2 + (y - src[:, 1].reshape(-1, 1, 1)) ** 2
    return secant_of_ray(model, r2, h, max_sine)


def secant_of_ray(model, r2: torch.Tensor, h: torch.Tensor, max_sine: float | None = None) -> torch.Tensor:
    """``1/cos θ = √(1 + r²/h²)`` of rays of squared lateral length ``r2`` (µm²) and height ``h`` (µm; broadcast),
    capped at the band limit's angle (``max_sine``, default ``model``'s plan's f_hi): :func:`ray_secant`'s rule, which
    the split-field model applies on the image alone."""
    sec = torch.sqrt(1.0 + r2 / (h * h))
    if max_sine is None:
        max_sine = model.plan.f_hi_per_um * model.optics.wavelength_um / model.optics.n_background
    return torch.clamp(sec, max=1.0 / math.sqrt(1.0 - max_sine**2))
