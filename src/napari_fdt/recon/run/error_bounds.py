"""Per-voxel error bounds of a finished run (``error_bounds``; issue 50): the run's result re-simulated and
reconstructed again along its path, then :func:`napari_fdt.recon.assess.bounds.bound`.

Each replicate: the images the result predicts (its Δn, calibrated sources, gains and optics: every part the run
kept, :func:`napari_fdt.recon.run.report.evaluate_images`), plus fresh noise at the data's own level (a variance
``a·image + b`` fitted to the run's residuals, so the model's misfit counts as noise too: the bound errs wide), are
reconstructed from the run's starting positions with the run's choices fixed
(:func:`napari_fdt.recon.run.half_sets.chosen_settings`: the TV weights and model parts it chose, no trials).

Cost: ``replicates`` runs without the trials (each about the run's stages; measured in docs/decisions/error-bounds.md).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.errors import FDTWarning
from napari_fdt.recon.assess.bounds import CALIBRATION, REPLICATES, BoundCalibration, bound
from napari_fdt.recon.run.half_sets import chosen_settings

if TYPE_CHECKING:
    from napari_fdt.recon.run.solver import Reconstructor

__all__ = ["REPLICATES", "NOISE_SAMPLE_PIXELS", "ErrorBounds", "noise_model", "replicate_images", "replicate_volumes", "error_bounds"]

#: Most pixels :func:`noise_model` reads (whole images, evenly spaced through the stack): a full-size stack's
#: residuals in float64 would take gigabytes for two numbers.
NOISE_SAMPLE_PIXELS = 1 << 22


def noise_model(images: np.ndarray, predictions: np.ndarray, bins: int = 32) -> tuple[float, float]:
    """``(a, b)`` with the residuals' variance ≈ a · prediction + b (shot noise and a floor: read noise and misfit),
    fitted by least squares over ``bins`` quantile bins of the prediction, both ≥ 0; intensity units. Reads at most
    :data:`NOISE_SAMPLE_PIXELS` pixels (whole images, evenly spaced)."""
    n = len(predictions)
    per_image = max(1, int(np.prod(np.shape(predictions)[1:])))
    take = np.unique(np.linspace(0, n - 1, max(1, min(n, NOISE_SAMPLE_PIXELS // per_image))).round().astype(int))
    pred = np.asarray(predictions[take], dtype=np.float64).ravel()
    res2 = (np.asarray(images[take], dtype=np.float64).ravel() - pred) ** 2
    edges = np.unique(np.quantile(pred, np.linspace(0, 1, bins + 1)))
    which = np.clip(np.searchsorted(edges, pred, side="right") - 1, 0, max(0, len(edges) - 2))
    count = np.bincount(which, minlength=len(edges) - 1).astype(np.float64)
    keep = count > 0
    x = (np.bincount(which, pred, minlength=len(count)) / np.maximum(count, 1))[keep]
    y = (np.bincount(which, res2, minlength=len(count)) / np.maximum(count, 1))[keep]
    if x.size >= 2 and np.ptp(x) > 0:
        a, b = np.polyfit(x, y, 1)
        if a < 0:
            a, b = 0.0, float(y.mean())
        elif b < 0:
            a, b = float((x * y).sum() / (x * x).sum()), 0.0
    else:
        a, b = 0.0, float(y.mean()) if y.size else 0.0
    return float(max(a, 0.0)), float(max(b, 0.0))


def replicate_images(predictions: np.ndarray, noise: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """``predictions`` (N, H, W) plus Gaussian noise of variance ``a·prediction + b``, clipped at 0; float32, made
    image by image (no float64 copy of the stack)."""
    a, b = noise
    out = np.empty(np.shape(predictions), dtype=np.float32)
    for i in range(len(out)):
        p = np.asarray(predictions[i], dtype=np.float64)
        out[i] = np.clip(p + np.sqrt(np.clip(a * p, 0, None) + b) * rng.standard_normal(p.shape), 0, None)
    return out


@dataclass
class ErrorBounds:
    """The bound (``bound``: (n_slices, H, W), Δn units), how it was made and what it cost."""

    bound: np.ndarray
    replicates: int
    noise: tuple[float, float]
    calibration: BoundCalibration
    seconds: float

    def to_dict(self, path: str | None = None) -> dict[str, Any]:
        """The report's ``error_bounds`` section (``path``: the bound's file, where written)."""
        c = self.calibration
        return {"path": path, "level": c.level, "units": "refractive index (|Δn − Δn_true| ≤ bound)",
                "method": "parametric bootstrap: the result re-simulated and reconstructed along the run's path "
                          f"({self.replicates} times); bias + spread over {c.slices} slices × {c.pixels}² px, plus "
                          f"{c.alpha:g} × the largest |Δn| there; × {c.q:.4g} (split-conformal)",
                "calibration": {"scenes": c.scenes, "source": c.source, "q": c.q, "slices": c.slices, "pixels": c.pixels,
                                "alpha": c.alpha},
                "noise_model": {"shot": self.noise[0], "floor": self.noise[1]},
                "replicates": self.replicates, "seconds": round(self.seconds, 2),
                "mean_bound": float(self.bound.mean()), "max_bound": float(self.bound.max())}


def replicate_volumes(rec: Reconstructor, replicates: int = REPLICATES, *, seed: int | None = None,
                      should_stop: Callable[[], bool] | None = None, on_replicate: Callable[[int], None] | None = None
                      ) -> tuple[np.ndarray, tuple[float, float]] | None:
    """The Δn volumes (K, n_slices, H, W) of ``replicates`` re-simulations of ``rec``'s result, reconstructed with its
    choices fixed on its device, and the noise model used; None when ``should_stop`` stopped one."""
    from napari_fdt.recon.run.report import evaluate_images
    from napari_fdt.recon.run.solver import Reconstructor

    acq = rec.acquisition
    preds, _ = evaluate_images(rec)
    noise = noise_model(acq.images, preds)
    rng = np.random.default_rng(rec.config.seed + 7919 if seed is None else seed)
    config = dataclasses.replace(chosen_settings(rec), error_bounds=False)
    volumes = []
    for k in range(replicates):
        if on_replicate is not None:
            on_replicate(k)
        sub = Acquisition(images=replicate_images(preds, noise, rng), optics=acq.optics, sources_um=acq.sources_um,
                          extra=dict(acq.extra))
        with warnings.catch_warnings():  # what the run said of the data it said once
            warnings.simplefilter("ignore", FDTWarning)
            rep = Reconstructor(sub, config, device=rec.device, initial_sources_um=rec.initial_sources_um)
            for _ in rep.run(should_stop=should_stop):
                pass
        if rep.completed_stages < len(rep.config.stages):
            return None
        volumes.append(rep.delta_n_full())
    return np.stack(volumes), noise


def error_bounds(rec: Reconstructor, replicates: int = REPLICATES, *, calibration: BoundCalibration = CALIBRATION,
                 should_stop: Callable[[], bool] | None = None,
                 on_replicate: Callable[[int], None] | None = None) -> ErrorBounds | None:
    """The bound of ``rec``'s finished result (:func:`replicate_volumes`, then
    :func:`napari_fdt.recon.assess.bounds.bound`); None when stopped."""
    t0 = time.perf_counter()
    made = replicate_volumes(rec, replicates, should_stop=should_stop, on_replicate=on_replicate)
    if made is None:
        return None
    volumes, noise = made
    return ErrorBounds(bound(rec.delta_n_full(), volumes, calibration), replicates, noise, calibration,
                       time.perf_counter() - t0)
