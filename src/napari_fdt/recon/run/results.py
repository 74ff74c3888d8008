"""What a run gives back: the volume on the acquisition's grid, the calibrated sources and gains, and the images its
current state predicts.

A mixin of :class:`~napari_fdt.recon.run.solver.Reconstructor` (one concern per module); it reads the run's ``volume``,
``volume_factor``, ``full_shape``, ``acquisition``, ``calibration``, ``image_scale``, ``images``, ``device``,
``stage_spec`` and ``_predict_normalised``.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from napari_fdt.recon.problem.stages import Stage, build_stage

__all__ = ["RunResults"]


class RunResults:
    """The results of a run, read at any time (a snapshot's, the last complete stage's after a cancel, the end's)."""

    def delta_n_full(self) -> np.ndarray:
        """Δn of the current grid on the acquisition grid (n_slices, H, W), float32."""
        if self.volume is None:
            raise RuntimeError("nothing reconstructed yet")
        return self.volume.full_resolution(self.volume_factor, self.full_shape).cpu().numpy().astype(np.float32)

    def ri_full(self) -> np.ndarray:
        """Absolute RI on the acquisition grid (n_slices, H, W), float32."""
        return (self.acquisition.optics.n_background + self.delta_n_full()).astype(np.float32)

    def sources_um(self) -> np.ndarray:
        """(N, 3) calibrated source positions (depth offset applied), float64, µm, acquisition coordinates."""
        return self.calibration.sources_um()

    def gains(self) -> np.ndarray:
        """(N,) calibrated gains in the acquisition's intensity units per model unit, float64."""
        return self.calibration.gains() * self.image_scale

    def evaluation_stage(self) -> Stage:
        """The multi-slice model on the acquisition grid (factor 1) for the current calibrated sources, with the run's model
        options (its camera, pupil edge, obliquity and sub-slices: the images the run fitted), for :meth:`predict`."""
        options = {**self.stage_spec(-1, factor=1).model_options(), "backward_mode": "auto"}
        return build_stage(-1, 1, 0, self.acquisition.optics, self.images, self.sources_um(), device=self.device, **options)

    def predict(self, indices: Sequence[int] | np.ndarray | torch.Tensor, stage: Stage | None = None) -> np.ndarray:
        """Images (B, h, w) float32 of images ``indices`` (B,) as the current state predicts them, without autograd.

        In the acquisition's intensity units (calibrated gains, sources and optics applied). ``stage``:
        None (default) is :meth:`evaluation_stage`, the acquisition grid (build it once and pass it when
        predicting many batches); a stage of the run gives images on its field grid, the volume taken at that
        stage's factor (it must be the current grid's factor, or 1).
        """
        if self.volume is None:
            raise RuntimeError("nothing reconstructed yet")
        stage = self.evaluation_stage() if stage is None else stage
        if stage.factor != 1 and stage.factor != self.volume_factor:
            raise ValueError(f"the volume is on a factor-{self.volume_factor} grid; predict on a stage of factor "
                             f"{self.volume_factor} or 1, not {stage.factor}")
        idx = torch.as_tensor(indices if isinstance(indices, torch.Tensor) else np.asarray(indices, dtype=np.int64),
                              dtype=torch.long).reshape(-1).to(self.device)
        with torch.no_grad():
            dn = self.volume.full_resolution(self.volume_factor, self.full_shape) if stage.factor == 1 else self.volume.delta_n()
            return (self._predict_normalised(stage, dn, idx) * self.image_scale).cpu().numpy()
