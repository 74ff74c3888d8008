"""Low-order aberrations of the objective: a pupil phase made of a few Zernike modes.

Convention (``docs/physics.md`` §3, "Aberrations"): the camera-side pupil is multiplied by ``exp(+i·W)`` with

    W(ρ, φ) = Σ_j c_j · Z_j(ρ, φ)      (radians),

``ρ = |f| / (NA/λ)`` the lateral frequency over the *nominal* pupil radius (the acquisition's NA, also when the
NA is calibrated), ``φ = atan2(fy, fx)`` (fx along image columns, fy along rows), and ``Z_j`` Noll-normalised
(RMS 1 over the unit disc, so ``c_j`` is the RMS wavefront error of the mode, in radians):

| name | Noll j | Z_j |
|---|---|---|
| ``defocus`` | 4 | √3·(2ρ² − 1) |
| ``astigmatism_oblique`` | 5 | √6·ρ²·sin 2φ |
| ``astigmatism_vertical`` | 6 | √6·ρ²·cos 2φ |
| ``coma_vertical`` | 7 | √8·(3ρ³ − 2ρ)·sin φ |
| ``coma_horizontal`` | 8 | √8·(3ρ³ − 2ρ)·cos φ |
| ``spherical`` | 11 | √5·(6ρ⁴ − 6ρ² + 1) |

The polynomials are evaluated beyond ρ = 1 too (the soft edge of the pupil). A positive ``defocus`` acts, to
paraxial order, like moving the camera's focal plane deeper (``image_plane_um`` larger) by
``2√3·c·n_b·λ/(π·NA²)`` µm (1.45 µm per radian at λ 0.635, NA 0.8, n_b 1.33).
"""

from __future__ import annotations

import math
from typing import Mapping, Sequence

import torch

from napari_fdt.errors import FDTInputError

__all__ = ["ZERNIKE_MODES", "RADIAL_MODES", "zernike_phase", "coefficients_vector", "parse_aberrations"]

#: The modes offered, in the order of a coefficient vector.
ZERNIKE_MODES: tuple[str, ...] = (
    "defocus", "astigmatism_oblique", "astigmatism_vertical", "coma_vertical", "coma_horizontal", "spherical",
)
#: The rotationally symmetric modes (the exact free field, :mod:`napari_fdt.physics.free_field`, holds them).
RADIAL_MODES: tuple[str, ...] = ("defocus", "spherical")


def _mode(name: str, rho2: torch.Tensor, fy: torch.Tensor, fx: torch.Tensor, f_abs: torch.Tensor, cutoff) -> torch.Tensor:
    if name == "defocus":
        return math.sqrt(3.0) * (2.0 * rho2 - 1.0)
    if name == "spherical":
        return math.sqrt(5.0) * (6.0 * rho2 * rho2 - 6.0 * rho2 + 1.0)
    if name in ("astigmatism_oblique", "astigmatism_vertical"):
        # ρ²·sin 2φ = 2·fx·fy/c², ρ²·cos 2φ = (fx² − fy²)/c²
        c2 = cutoff * cutoff
        val = 2.0 * fx * fy / c2 if name == "astigmatism_oblique" else (fx * fx - fy * fy) / c2
        return math.sqrt(6.0) * val
    if name in ("coma_vertical", "coma_horizontal"):
        # (3ρ³ − 2ρ)·sin φ = (3ρ² − 2)·fy/c
        comp = fy if name == "coma_vertical" else fx
        return math.sqrt(8.0) * (3.0 * rho2 - 2.0) * comp / cutoff
    raise FDTInputError("aberrations", f"unknown Zernike mode {name!r}", f"use one of {', '.join(ZERNIKE_MODES)}")


def zernike_phase(
    fy: torch.Tensor,
    fx: torch.Tensor,
    na: float,
    wavelength_um: float | torch.Tensor,
    coefficients: torch.Tensor | Sequence[float],
    modes: Sequence[str] = ZERNIKE_MODES,
) -> torch.Tensor:
    """Pupil phase W (radians) on the frequency grid; fy (Hp, 1), fx (1, Wp) in cycles/µm → (Hp, Wp).

    ``coefficients``: one per entry of ``modes`` (radians, Noll-normalised), a tensor for calibration.
    ``na``: the nominal NA that defines ρ = 1.
    """
    cutoff = na / wavelength_um
    f2 = fy * fy + fx * fx
    rho2 = f2 / (cutoff * cutoff)
    f_abs = torch.sqrt(f2)
    coeffs = coefficients if isinstance(coefficients, torch.Tensor) else torch.tensor(list(coefficients), dtype=f2.dtype, device=f2.device)
    out = torch.zeros_like(f2 + 0.0 * fx)
    for j, name in enumerate(modes):
        out = out + coeffs[j] * _mode(name, rho2, fy, fx, f_abs, cutoff)
    return out


def coefficients_vector(aberrations: Mapping[str, float] | None) -> list[float]:
    """The coefficients of :data:`ZERNIKE_MODES` from a ``{mode: radians}`` mapping (missing modes 0)."""
    aberrations = dict(aberrations or {})
    unknown = [k for k in aberrations if k not in ZERNIKE_MODES]
    if unknown:
        raise FDTInputError("aberrations", f"unknown Zernike mode {unknown[0]!r}", f"use one of {', '.join(ZERNIKE_MODES)}")
    vals = []
    for name in ZERNIKE_MODES:
        v = float(aberrations.get(name, 0.0))
        if not math.isfinite(v):
            raise FDTInputError("aberrations", f"{name} = {v} is not finite", "give the coefficient in radians")
        vals.append(v)
    return vals


def parse_aberrations(text: str | None) -> dict[str, float]:
    """``"spherical=0.5,defocus=-0.2"`` → ``{"spherical": 0.5, "defocus": -0.2}`` (radians); empty → {}."""
    out: dict[str, float] = {}
    if not text:
        return out
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        name, sep, value = part.partition("=")
        name = name.strip()
        try:
            out[name] = float(value) if sep else float("nan")
        except ValueError:
            raise FDTInputError("aberrations", f"{part!r} is not MODE=RADIANS", "e.g. spherical=0.5,defocus=-0.2") from None
    coefficients_vector(out)  # validates names and values
    return out
