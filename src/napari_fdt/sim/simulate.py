"""Simulated acquisitions: source grids, the forward model in batches, and a realistic measurement.

The measurement model (``docs/physics.md``, "Simulated measurement"): image i is
``Poisson(scale · b_i · I_i) + Normal(0, read_noise²)``, clipped at 0, where ``I_i`` is the forward
model's image for the true source, ``b_i`` a per-source brightness drawn log-normally (median 1,
log-standard deviation ``brightness_spread``) and ``scale`` sets the mean photo-electron count of a
unit-brightness image to ``photons``. The acquisition's ``sources_um`` are the true positions plus
Gaussian jitter, as an imperfect initial estimate. With an emission bandwidth, ``I_i`` is the
incoherent sum of the model's images over a Gauss–Hermite sampling of the emission spectrum
(:mod:`napari_fdt.model.coherence`): temporally partially coherent light, whose far fringes wash out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.errors import FDTInputError
from napari_fdt.model.coherence import coherence_length_um, emission_spectrum
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.model.oversampled import OversampledModel
from napari_fdt.model.render import render_images
from napari_fdt.physics.aberrations import ZERNIKE_MODES
from napari_fdt.physics.camera import resolve_pixel_integration
from napari_fdt.physics.grid import GridPlan, plan_for_sources
from napari_fdt.physics.optics import Optics
from napari_fdt.sim.phantoms import bead_phantom, cell_phantom, fibre_phantom, text_phantom

__all__ = ["source_grid", "simulate_measurement", "make_scene", "Simulation", "simulate"]


def source_grid(n_per_side: int, span_um: float, depth_um: float) -> np.ndarray:
    """An n×n grid of sources spanning ``[-span/2, span/2]`` in x and y, all ``depth_um`` deep; (n², 3) in µm.

    Ordered row by row (y outer, x inner). One source sits at the centre when n is 1.
    """
    if int(n_per_side) < 1:
        raise FDTInputError("sources", f"must be >= 1 per side, got {n_per_side}", "give the grid's side, e.g. 8 for 64 sources")
    if not (math.isfinite(depth_um) and depth_um > 0):
        raise FDTInputError("depth_um", f"must be positive, got {depth_um}", "sources lie below the volume's bottom face")
    if not (math.isfinite(span_um) and span_um >= 0):
        raise FDTInputError("span_um", f"must be >= 0, got {span_um}", "give the grid's lateral extent in µm")
    n = int(n_per_side)
    c = np.linspace(-span_um / 2, span_um / 2, n) if n > 1 else np.zeros(1)
    yy, xx = np.meshgrid(c, c, indexing="ij")
    return np.column_stack([xx.ravel(), yy.ravel(), np.full(n * n, float(depth_um))])


def simulate_measurement(
    clean: np.ndarray,
    *,
    photons: float = 2000.0,
    read_noise: float = 2.0,
    brightness_spread: float = 0.2,
    rng: np.random.Generator | int | None = 0,
    noise: bool = True,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Turn noise-free unit-brightness images (N, H, W) into camera counts.

    Returns ``(images float32 photo-electrons, brightness (N,), scale)``. With ``noise=False`` the images are
    the scaled expectations.
    """
    if not (photons > 0 and math.isfinite(photons)):
        raise FDTInputError("photons", f"must be positive, got {photons}", "mean photo-electrons per pixel, e.g. 2000")
    if read_noise < 0 or brightness_spread < 0:
        raise FDTInputError("read_noise" if read_noise < 0 else "brightness_spread", "must be >= 0", "use 0 to switch it off")
    rng = np.random.default_rng(rng)
    n = clean.shape[0]
    brightness = np.exp(brightness_spread * rng.standard_normal(n))
    scale = float(photons) / float(clean.mean(dtype=np.float64))
    expected = clean.astype(np.float64) * (scale * brightness)[:, None, None]
    if not noise:
        return expected.astype(np.float32), brightness, scale
    counts = rng.poisson(expected).astype(np.float64)
    if read_noise > 0:
        counts += rng.normal(0.0, read_noise, size=counts.shape)
    return np.clip(counts, 0, None).astype(np.float32), brightness, scale


def make_scene(
    name: str,
    shape: tuple[int, int],
    optics: Optics,
    *,
    delta_n: float | None = None,
    text: str = "UCDAVIS",
    letter_height_px: int | None = None,
    rng: np.random.Generator | int | None = 0,
) -> np.ndarray:
    """Contrast volume Δn (n_slices, H, W) of a named scene: ``letters``, ``beads``, ``cells`` or ``fibres``."""
    n, dx, dz = optics.n_slices, optics.pixel_size_um, optics.slice_spacing_um
    if name == "letters":
        return text_phantom(shape, n, text=text, delta_n=0.05 if delta_n is None else delta_n, letter_height_px=letter_height_px)
    if name == "beads":
        return bead_phantom(shape, n, dx, dz, delta_n=0.03 if delta_n is None else delta_n, rng=rng)
    if name == "cells":
        kw = {} if delta_n is None else {"delta_n_cytoplasm": delta_n}
        return cell_phantom(shape, n, dx, dz, rng=rng, **kw)
    if name == "fibres":
        return fibre_phantom(shape, n, dx, dz, delta_n=0.03 if delta_n is None else delta_n, rng=rng)
    raise FDTInputError("scene", f"unknown scene {name!r}", "choose letters, beads, cells or fibres")


@dataclass
class Simulation:
    """A simulated acquisition and its ground truth.

    ``ri`` is the absolute RI (n_slices, H, W) float32; ``sources_um`` the true positions (N, 3);
    ``brightness`` (N,) and ``scale`` such that the expected image i is ``scale · brightness_i · model image``.
    """

    acquisition: Acquisition
    ri: np.ndarray
    sources_um: np.ndarray
    brightness: np.ndarray
    scale: float
    plan: GridPlan
    settings: dict = field(default_factory=dict)

    def truth_metadata(self) -> dict:
        """Content of ``ground_truth_sources_um.json``."""
        return {
            "sources_um": self.sources_um.tolist(),
            "brightness": self.brightness.tolist(),
            "photon_scale": self.scale,
            "gain": (self.scale * self.brightness).tolist(),
            "settings": self.settings,
        }


def _json_length(value: float) -> float | None:
    """A length for JSON: None stands for infinity (JSON has no inf)."""
    return None if math.isinf(value) else float(value)


def simulate(
    delta_n: np.ndarray,
    optics: Optics,
    sources_um: np.ndarray,
    *,
    photons: float = 2000.0,
    read_noise: float = 2.0,
    brightness_spread: float = 0.2,
    jitter_xy_um: float = 1.0,
    jitter_depth_um: float = 1.0,
    noise: bool = True,
    seed: int = 0,
    device: str = "auto",
    batch_size: int = 16,
    uint16: bool = False,
    bandwidth_um: float = 0.0,
    n_wavelengths: int = 9,
    pixel_integration: bool | str = False,
    pupil_edge: float | None = None,
    aberrations: dict[str, float] | None = None,
    sub_slices: int = 1,
    field_oversampling: int = 1,
) -> Simulation:
    """Simulate an acquisition of ``delta_n`` (n_slices, H, W) lit by ``sources_um`` (N, 3).

    ``bandwidth_um`` is the FWHM of a Gaussian emission spectrum centred on ``optics.wavelength_um``
    (0: monochromatic, coherent); the clean images are then the spectral sum over ``n_wavelengths``
    Gauss–Hermite wavelengths (``n_wavelengths`` times the cost). Both are recorded in the settings.

    The camera and objective (``docs/physics.md`` §3): ``pixel_integration`` (``"auto"``: on when 2·NA/λ exceeds
    the camera's Nyquist 1/(2·dx)) averages the intensity over each pixel; ``pupil_edge`` is the pupil's soft edge
    (None: the default 0.03; 0: a hard pupil, held exactly); ``aberrations`` ``{Zernike mode: radians}`` a pupil
    phase. ``pixel_integration`` and ``pupil_edge`` go to ``acquisition.json`` (the camera and objective the
    solver models by default); the aberrations only to the ground truth's settings (the solver calibrates them).
    ``sub_slices``: screens per slice (:class:`~napari_fdt.model.forward.MultiSliceModel`): 4 makes images of a
    continuous slab to about 0.25 % where one thin screen per 2 µm slice is 5 % off (docs/physics.md, "Sub-slices");
    recorded in the ground truth's settings only (it is how the data were made, not a property of the microscope).
    ``field_oversampling`` 2: the field on a grid twice as fine as the camera's
    (:class:`~napari_fdt.model.oversampled.OversampledModel`; the camera grid is percents off where the sample scatters
    beyond its Nyquist, docs/physics.md, "A finer field grid"); recorded in the ground truth's settings only.
    """
    wavelengths, weights = emission_spectrum(optics.wavelength_um, bandwidth_um, n_wavelengths)
    delta_n = np.asarray(delta_n, dtype=np.float32)
    if delta_n.ndim != 3 or delta_n.shape[0] != optics.n_slices:
        raise FDTInputError("delta_n", f"must be (n_slices={optics.n_slices}, H, W), got {delta_n.shape}", "match n_slices")
    src = np.asarray(sources_um, dtype=np.float64).reshape(-1, 3)
    shape = delta_n.shape[1:]
    plan = plan_for_sources(optics, shape, src)
    integrate = resolve_pixel_integration(pixel_integration, optics.na, optics.wavelength_um, optics.pixel_size_um)
    if field_oversampling not in (1, 2):
        raise FDTInputError("field_oversampling", f"must be 1 or 2, got {field_oversampling!r}",
                            "1 (the field on the camera grid) or 2 (a grid twice as fine)")
    model_class = OversampledModel if field_oversampling == 2 else MultiSliceModel
    model = model_class(optics, plan, device=device, pupil_edge=pupil_edge, aberrations=aberrations,
                        pixel_integration=integrate, sub_slices=sub_slices)
    spectrum = {} if len(wavelengths) == 1 else dict(wavelengths_um=wavelengths, weights=weights)
    clean = render_images(model, delta_n, src, batch_size=batch_size, **spectrum)
    rng = np.random.default_rng(seed)
    images, brightness, scale = simulate_measurement(
        clean, photons=photons, read_noise=read_noise, brightness_spread=brightness_spread, rng=rng, noise=noise
    )
    if uint16:
        if images.max() > 65535:
            raise FDTInputError("photons", f"images reach {images.max():.0f} counts, beyond uint16", "lower --photons or write float32")
        images = np.rint(images).astype(np.uint16)
    estimate = src.copy()
    estimate[:, :2] += jitter_xy_um * rng.standard_normal((len(src), 2))
    estimate[:, 2] = np.maximum(estimate[:, 2] + jitter_depth_um * rng.standard_normal(len(src)), 0.1 * src[:, 2])
    settings = dict(photons=photons, read_noise=read_noise, brightness_spread=brightness_spread,
                    jitter_xy_um=jitter_xy_um, jitter_depth_um=jitter_depth_um, noise=noise, seed=seed,
                    bandwidth_um=float(bandwidth_um), n_wavelengths=int(n_wavelengths),
                    emission_wavelengths_um=[float(v) for v in wavelengths],
                    emission_weights=[float(v) for v in weights],
                    coherence_length_um=_json_length(coherence_length_um(optics.wavelength_um, bandwidth_um, optics.n_background)),
                    pixel_integration=integrate, pupil_edge=model.pupil_edge,
                    aberrations={k: v for k, v in zip(ZERNIKE_MODES, model.zernike) if v}, sub_slices=model.sub_slices,
                    field_oversampling=int(field_oversampling))
    extra = {"simulated": settings, "pixel_integration": integrate, "pupil_edge": model.pupil_edge}
    acq = Acquisition(images=images, optics=optics, sources_um=estimate, extra=extra)
    ri = (optics.n_background + delta_n).astype(np.float32)
    return Simulation(acq, ri, src, brightness, scale, plan, settings)
