"""The explicit RI grid: voxels as parameters, a bounded activation, resampling between stages.

Activations (``Δn = n − n_b``):

* ``"paper"`` (default): ``Δn = 2·Δn_max·ReLU(sigmoid(x) − 1/2)`` ∈ [0, Δn_max), the paper's map scaled to
  a physical bound. Its gradient vanishes for x ≤ 0 (a voxel pushed to 0 stays there: sparsity), and at
  x = 0 exactly, so the grid starts slightly positive and resampling re-inverts with a floor
  (``floor_fraction·Δn_max``) so every voxel of a new stage can move.
* ``"signed"``: ``Δn = Δn_max·(2·sigmoid(x) − 1)`` ∈ (−Δn_max, Δn_max), for samples with lower-index parts.

The grid's lateral sampling is the stage's (``factor`` × the acquisition's pixel); its pixel (j) centre
sits at fine pixel ``j·factor + (factor − 1)/2``, the centre of the block it averages.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from napari_fdt.errors import FDTInputError

__all__ = ["RIVolume", "ACTIVATIONS", "upsample_to"]

ACTIVATIONS = ("paper", "signed")


def upsample_to(volume: torch.Tensor, factor: int, shape: tuple[int, int]) -> torch.Tensor:
    """Bilinear upsampling of (Z, h, w) by an integer ``factor`` to (Z, H, W), block-centre geometry.

    Pixels beyond ``h·factor`` (``H`` not a multiple of the factor) repeat the last row/column.
    """
    z, h, w = volume.shape
    if factor == 1 and (h, w) == tuple(shape):
        return volume
    up = F.interpolate(volume[None], size=(h * factor, w * factor), mode="bilinear", align_corners=False)[0]
    ph, pw = shape[0] - h * factor, shape[1] - w * factor
    if ph < 0 or pw < 0:
        return up[:, : shape[0], : shape[1]]
    if ph or pw:
        up = F.pad(up[None], (0, pw, 0, ph), mode="replicate")[0]
    return up


class RIVolume:
    """Parameters of the RI contrast on a (n_slices, h, w) grid.

    Parameters
    ----------
    shape: (n_slices, h, w).
    delta_n_max: bound of |Δn| (> 0).
    activation: ``"paper"`` or ``"signed"``.
    device, dtype: of the parameter tensor.
    init_delta_n: initial contrast (uniform), default a small positive value for ``"paper"``, 0 for ``"signed"``.
    """

    def __init__(
        self,
        shape: tuple[int, int, int],
        *,
        delta_n_max: float = 0.1,
        activation: str = "paper",
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
        init_delta_n: float | None = None,
        floor_fraction: float = 1e-3,
    ) -> None:
        if activation not in ACTIVATIONS:
            raise FDTInputError("activation", f"unknown activation {activation!r}", f"choose one of {', '.join(ACTIVATIONS)}")
        if not (math.isfinite(delta_n_max) and delta_n_max > 0):
            raise FDTInputError("delta_n_max", f"must be positive, got {delta_n_max}", "give the largest expected |Δn|, e.g. 0.1")
        self.delta_n_max = float(delta_n_max)
        self.activation = activation
        self.floor_fraction = float(floor_fraction)
        if init_delta_n is None:
            init_delta_n = 0.0
        dn = torch.full(tuple(shape), float(init_delta_n), device=device, dtype=dtype)
        self.x = self._inverse(dn).requires_grad_()

    # -- activation ---------------------------------------------------------------------------
    def _inverse(self, delta_n: torch.Tensor) -> torch.Tensor:
        m = self.delta_n_max
        if self.activation == "paper":
            u = torch.clamp(delta_n / m, self.floor_fraction, 1.0 - 1e-4)
            return torch.logit(0.5 + 0.5 * u)
        u = torch.clamp(delta_n / m, -(1.0 - 1e-4), 1.0 - 1e-4)
        return torch.logit(0.5 + 0.5 * u)

    def delta_n(self) -> torch.Tensor:
        """Δn on the grid, (n_slices, h, w), differentiable in :attr:`x`."""
        m = self.delta_n_max
        if self.activation == "paper":
            return (2.0 * m) * torch.relu(torch.sigmoid(self.x) - 0.5)
        return m * (2.0 * torch.sigmoid(self.x) - 1.0)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.x.shape)

    # -- stages -------------------------------------------------------------------------------
    def resample(self, factor_from: int, factor_to: int, full_shape: tuple[int, int]) -> None:
        """Move to a finer (or equal) stage grid: Δn is upsampled, then the activation re-inverted (with floor).

        ``full_shape`` is the acquisition's (H, W); the new grid is (H // factor_to, W // factor_to).
        """
        if factor_from % factor_to:
            raise FDTInputError("stages", f"factor {factor_from} is not a multiple of the next stage's {factor_to}",
                                "use factors that divide each other, e.g. 4, 2, 1")
        with torch.no_grad():
            dn = self.delta_n()
            ratio = factor_from // factor_to
            new_hw = (full_shape[0] // factor_to, full_shape[1] // factor_to)
            dn = upsample_to(dn, ratio, new_hw)
            self.x = self._inverse(dn).detach().requires_grad_()

    def full_resolution(self, factor: int, full_shape: tuple[int, int]) -> torch.Tensor:
        """Δn upsampled to the acquisition grid (n_slices, H, W), detached."""
        with torch.no_grad():
            return upsample_to(self.delta_n(), factor, full_shape)

    def state_dict(self) -> dict:
        return {"x": self.x.detach().cpu(), "delta_n_max": self.delta_n_max, "activation": self.activation,
                "floor_fraction": self.floor_fraction}

    @classmethod
    def from_state_dict(cls, state: dict, device, dtype) -> "RIVolume":
        vol = cls(tuple(state["x"].shape), delta_n_max=state["delta_n_max"], activation=state["activation"],
                  device=device, dtype=dtype, floor_fraction=state["floor_fraction"])
        vol.x = state["x"].to(device, dtype).requires_grad_()
        return vol
