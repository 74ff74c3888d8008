"""Obliquity error of the thin phase screen, measured with the package's MultiSliceModel against the exact slab.

Run from the repository root::

    python -m benchmarks run obliquity          # prints the tables of docs/physics.md §6 (Markdown)

A uniform slab of contrast Δn fills the volume (the whole window, so it is laterally infinite): every plane-wave
component then picks up exactly ``φ_exact(f) = 2π·T·(sqrt((n_b+Δn)²/λ² − f²) − sqrt(n_b²/λ² − f²))`` (reflections
aside), an exact reference for any source.

1. **Plane waves.** The model's phase per plane-wave component is measured as the argument of the ratio of the
   camera-field spectra with and without the slab (full window, float64), at the component nearest the pupil's
   edge ray ``sin θ = NA/n_b``, for several slice counts with the thickness fixed; compared with ``φ_exact`` and
   the first-order prediction ``φ_exact/φ_screen − 1 ≈ 1/cos θ − 1``.
2. **Images.** A point source 20 µm below the slab; the exact camera field is the homogeneous one with
   ``exp(i·φ_exact(f))`` applied per component. Relative L2 image error of the model, of the model after
   refitting the source depth (what self-calibration could absorb: obliquity of a uniform slab acts like a focus
   shift), and of the two proposed corrections in :mod:`napari_fdt.physics.obliquity`.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time

import numpy as np
import torch

from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.physics.grid import plan_for_sources
from napari_fdt.physics.obliquity import obliquity_error, slab_phase_exact
from napari_fdt.physics.optics import Optics
from napari_fdt.physics.propagation import axial_frequency_offset, phase_screen, screen_phase

LAM, N_B, THICKNESS, DEPTH = 0.6, 1.33, 8.0, 20.0
NAS = (0.3, 0.45, 0.66, 0.8, 0.95)



# --- Proposals measured here (not in the package) ------------------------------------------------------------------

def oblique_camera_field(model, delta_n: torch.Tensor, sources_um: torch.Tensor) -> torch.Tensor:
    """Reference for ``MultiSliceModel(..., obliquity="per_source")``, written out from docs/physics.md §6.

    Same kernels, source spectrum, pupil and crop as ``model``; the screen of slice k for source i becomes
    ``exp(i·2π/λ·Δz·Δn·sec θ_i)`` with ``tan θ_i = r/(depth_i + (k + ½)·Δz)``, r the lateral distance from source i
    to the window pixel, sec θ capped at the band limit's angle. The secant is computed here in float64 numpy,
    independently of :func:`napari_fdt.model.forward.ray_secant`. Returns (B, H, W) complex.
    """
    k = model.kernels()
    dn = model.pad_volume(delta_n)
    hp, wp = model.plan.padded_shape
    dx = float(model.pixel_size_um)
    dz = float(k.slice_spacing_um)
    src = np.asarray(sources_um.detach().cpu(), dtype=np.float64)
    yy, xx = np.meshgrid((np.arange(hp) - hp // 2) * dx, (np.arange(wp) - wp // 2) * dx, indexing="ij")
    max_sine = model.plan.f_hi_per_um * model.optics.wavelength_um / model.optics.n_background
    sec_cap = 1.0 / math.sqrt(1.0 - max_sine**2)
    u = torch.fft.ifft2(model.source_spectrum(sources_um.to(model.device, model.dtype), k))
    for i in range(dn.shape[0]):
        if i:
            u = torch.fft.ifft2(torch.fft.fft2(u) * k.slice_kernel)
        h = src[:, 2, None, None] + (i + 0.5) * dz
        r2 = (xx[None] - src[:, 0, None, None]) ** 2 + (yy[None] - src[:, 1, None, None]) ** 2
        sec = np.minimum(np.sqrt(1.0 + r2 / h**2), sec_cap)
        u = u * phase_screen(dn[i] * torch.as_tensor(sec, dtype=dn.dtype, device=dn.device), dz, k.wavelength_um)
    u = torch.fft.ifft2(torch.fft.fft2(u) * k.exit_kernel)
    return model.crop(u)


def secant_screen_camera_field(model, delta_n: torch.Tensor, sources_um: torch.Tensor) -> torch.Tensor:
    """Proposal: the multi-slice model with each screen's scattered part weighted by ``1/cos θ`` of its direction.

    First-order (Born) scattering from a slab of thickness Δz carries the factor ``i·(2π/λ)·Δz·Δn / cos θ_out``,
    θ_out the direction of the scattered plane wave (``cos θ = λ·qz/n_b``); the thin screen omits ``1/cos θ_out``.
    Here a slice's step is ``u ← u + F⁻¹[sec(f)·F[(t − 1)·u]]`` with ``t`` the usual screen: exact to first order
    in Δn for any object, and for a uniform slab its error falls as 1/n_slices. Cost: one more FFT pair per slice.
    Returns (B, H, W) complex.
    """
    k = model.kernels()
    dn = model.pad_volume(delta_n)
    f2 = k.fy * k.fy + k.fx * k.fx
    offset, propagating = axial_frequency_offset(f2, model.optics.n_background, k.wavelength_um)
    k_b = model.optics.n_background / k.wavelength_um
    max_sec = 1.0 / math.sqrt(1.0 - 0.98**2)
    sec = torch.where(propagating, torch.clamp(k_b / (offset + k_b), max=max_sec), torch.zeros_like(f2))
    u = torch.fft.ifft2(model.source_spectrum(sources_um.to(model.device, model.dtype), k))
    for i in range(dn.shape[0]):
        if i:
            u = torch.fft.ifft2(torch.fft.fft2(u) * k.slice_kernel)
        t = phase_screen(dn[i], k.slice_spacing_um, k.wavelength_um) - 1.0
        u = u + torch.fft.ifft2(torch.fft.fft2(t * u) * sec)
    u = torch.fft.ifft2(torch.fft.fft2(u) * k.exit_kernel)
    return model.crop(u)

def optics_for(na: float, n_slices: int, thickness: float = THICKNESS) -> Optics:
    """Pixel at 90 % of the pupil's Nyquist limit (at most 0.5 µm)."""
    dx = min(0.5, 0.9 * LAM / (2 * na * 1.03))
    return Optics(wavelength_um=LAM, n_background=N_B, na=na, pixel_size_um=dx, n_slices=n_slices,
                  slice_spacing_um=thickness / n_slices)


def full_window_model(optics: Optics, src: np.ndarray) -> MultiSliceModel:
    """A float64 model whose 'image' is its whole window (so the camera field's spectrum is available)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plan = plan_for_sources(optics, (32, 32), src)
    plan = dataclasses.replace(plan, image_shape=plan.padded_shape, offset=(0, 0))
    return MultiSliceModel(optics, plan, device="cpu", dtype=torch.float64)


def measure_plane_wave(na: float, n_slices: int, dn: float) -> dict:
    """Model phase of the component nearest sin θ = NA/n_b (measured), the exact one, and the errors."""
    o = optics_for(na, n_slices)
    src = np.array([[0.0, 0.0, DEPTH]])
    model = full_window_model(o, src)
    hp, wp = model.plan.padded_shape
    slab = torch.full((n_slices, hp, wp), dn, dtype=torch.float64)
    s = torch.from_numpy(src)
    with torch.no_grad():
        u1 = torch.fft.fft2(model.camera_field(slab, s))[0]
        u0 = torch.fft.fft2(model.camera_field(torch.zeros_like(slab), s))[0]
    k = model.kernels()
    f2 = (k.fy * k.fy + k.fx * k.fx).expand(hp, wp)
    target = 0.97 * na / LAM  # inside the pupil's flat part (its soft edge starts at 0.97·NA/λ)
    mask = (u0.abs() > 1e-6 * u0.abs().max()) & (f2.sqrt() <= target)
    idx = torch.argmax(torch.where(mask, f2, torch.full_like(f2, -1.0)))
    f = float(f2.flatten()[idx].sqrt())
    phi_model = float(torch.angle(u1.flatten()[idx] / u0.flatten()[idx]))
    # every component inside the pupil has the same model phase (the screens commute with the propagation)
    spread = float((torch.angle(u1[mask] / u0[mask]) - phi_model).abs().max())
    sin_t = LAM * f / N_B
    phi_exact = float(slab_phase_exact(np.float64(f * f), dn, THICKNESS, N_B, LAM))
    return dict(na=na, n_slices=n_slices, sin_theta=sin_t, phi_model=phi_model, phi_screen=screen_phase(dn, THICKNESS, LAM),
                phi_exact=phi_exact, error=phi_exact / phi_model - 1.0, predicted=1.0 / math.sqrt(1 - sin_t**2) - 1.0,
                exact_formula=float(obliquity_error(np.float64(sin_t), dn, N_B)), spread=spread)


def _images(field: torch.Tensor) -> np.ndarray:
    return (field.real**2 + field.imag**2).numpy()


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def _gain_rel(a: np.ndarray, b: np.ndarray) -> float:
    """Relative error of ``a`` against ``b`` after the least-squares gain (the solver fits one per image)."""
    g = float((a * b).sum() / (a * a).sum())
    return _rel(g * a, b)


def disc_px(optics: Optics) -> int:
    """Pixels of an image holding the source's whole defocused disc at the camera (radius h·tan θ_NA, h = depth + T)."""
    s = optics.na / optics.n_background
    return 2 * math.ceil((DEPTH + THICKNESS) * s / math.sqrt(1 - s * s) / optics.pixel_size_um) + 8


def measure_image(na: float, n_slices: int, dn: float, refit: bool = True) -> dict:
    """Image errors of a point source under a uniform slab: model, model with the depth refitted, the two proposals.

    The image holds the whole defocused disc, so it sees every angle the pupil passes.
    """
    o = optics_for(na, n_slices)
    src = np.array([[0.0, 0.0, DEPTH]])
    model = full_window_model(o, src)
    image_px = min(disc_px(o), min(model.plan.padded_shape))
    hp, wp = model.plan.padded_shape
    c0, c1 = hp // 2 - image_px // 2, wp // 2 - image_px // 2
    crop = (slice(c0, c0 + image_px), slice(c1, c1 + image_px))
    slab = torch.full((n_slices, hp, wp), dn, dtype=torch.float64)
    s = torch.from_numpy(src)
    k = model.kernels()
    f2 = (k.fy * k.fy + k.fx * k.fx).expand(hp, wp)
    with torch.no_grad():
        u0 = model.camera_field(torch.zeros_like(slab), s)[0]
        exact_phase = torch.where(f2 < (N_B / LAM) ** 2, slab_phase_exact(torch.clamp(f2, max=(N_B / LAM) ** 2), dn,
                                                                          THICKNESS, N_B, LAM), torch.zeros_like(f2))
        exact = _images(torch.fft.ifft2(torch.fft.fft2(u0) * torch.polar(torch.ones_like(f2), exact_phase)))[crop]
        plain = _images(model.camera_field(slab, s)[0])[crop]
        ray = _images(oblique_camera_field(model, slab, s)[0])[crop]
        secant = _images(secant_screen_camera_field(model, slab, s)[0])[crop]
        out = dict(na=na, n_slices=n_slices, dx=o.pixel_size_um, image_px=image_px, model=_gain_rel(plain, exact),
                   ray_secant=_gain_rel(ray, exact), secant_screen=_gain_rel(secant, exact))
        if refit:  # the best source depth for the uncorrected model (a focus shift absorbs most of a uniform slab)
            def err(d: float) -> float:
                return _gain_rel(_images(model.camera_field(slab, torch.tensor([[0.0, 0.0, d]], dtype=torch.float64))[0])[crop], exact)

            grid = np.linspace(DEPTH - 2.0, DEPTH + 2.0, 9)
            errs = [err(d) for d in grid]
            lo, hi = grid[max(0, int(np.argmin(errs)) - 1)], grid[min(len(grid) - 1, int(np.argmin(errs)) + 1)]
            for _ in range(16):  # golden-section refinement, to 1 nm
                a, b = lo + 0.382 * (hi - lo), lo + 0.618 * (hi - lo)
                if err(a) < err(b):
                    hi = b
                else:
                    lo = a
            best = 0.5 * (lo + hi)
            out.update(refit_depth_shift_um=best - DEPTH, model_refit=err(best))
    return out


def main() -> int:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    torch.set_num_threads(2)
    t0 = time.perf_counter()
    dn = 0.02
    print(f"## Plane waves through a uniform slab (T = {THICKNESS:g} µm, Δn = {dn}, λ = {LAM} µm, n_b = {N_B})\n")
    print("| NA | sin θ | slices | model phase (rad) | spread over the pupil (rad) | exact phase (rad) | "
          "error φ_exact/φ_model − 1 | 1/cos θ − 1 |")
    print("|---|---|---|---|---|---|---|---|")
    for na in NAS:
        for n in (1, 4, 16):
            r = measure_plane_wave(na, n, dn)
            print(f"| {na:g} | {r['sin_theta']:.3f} | {n} | {r['phi_model']:.4f} | {r['spread']:.1e} | "
                  f"{r['phi_exact']:.4f} | {100 * r['error']:.1f} % | {100 * r['predicted']:.1f} % |", flush=True)
    print(f"\n## Image of a point source {DEPTH:g} µm under the slab (the whole defocused disc; relative L2 after a "
          "least-squares gain)\n")
    print("| NA | image (px of µm) | slices | model | model, depth refitted (shift) | per-source 1/cos θ screens | "
          "secant-weighted screens |")
    print("|---|---|---|---|---|---|---|")
    for na in NAS:
        for n in ((2, 8, 32) if na == 0.8 else (8,)):
            r = measure_image(na, n, dn)
            print(f"| {na:g} | {r['image_px']} of {r['dx']:.3f} | {n} | {100 * r['model']:.2f} % | {100 * r['model_refit']:.2f} % "
                  f"({r['refit_depth_shift_um']:+.2f} µm) | {100 * r['ray_secant']:.2f} % | {100 * r['secant_screen']:.2f} % |",
                  flush=True)
    print(f"\n({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
