"""Optional CUDA-graph capture of a model's forward and backward pass (CUDA only).

A coarse stage does little arithmetic per operation, so on a GPU its time can go to launching kernels rather
than running them. :func:`graphed_model` records one forward and one backward pass of an
:class:`~napari_fdt.model.protocol.ImageModel` for fixed shapes with :func:`torch.cuda.make_graphed_callables`
and replays them: one launch per pass. The inputs must keep their shapes, dtypes and ``requires_grad`` flags
between calls (a fixed batch size); optics overrides are not captured. Used by
``benchmarks/coarse_stage_speed.py --cuda-graph``; not wired into the solver (not yet timed on a GPU), so it lives with
the benchmarks.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

__all__ = ["graphed_model", "can_graph"]


def can_graph(device: torch.device | str) -> bool:
    """True when ``device`` is a CUDA device and CUDA is available (graphs do not exist elsewhere)."""
    return torch.device(device).type == "cuda" and torch.cuda.is_available()


def graphed_model(model, delta_n: torch.Tensor, sources_um: torch.Tensor, gain: torch.Tensor,
                  *, warmup_iters: int = 3) -> Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]:
    """``f(delta_n, sources_um, gain) → images``, the model's pass captured in CUDA graphs for these example inputs.

    ``delta_n`` (n, h, w), ``sources_um`` (B, 3), ``gain`` (B,): example tensors on the model's CUDA device with the
    ``requires_grad`` flags of the real calls. Raises ``ValueError`` off CUDA.
    """
    if not can_graph(model.device):
        raise ValueError(f"CUDA graphs need a CUDA device; the model is on {model.device}")

    def images(d: torch.Tensor, s: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        return model(d, s, g)

    return torch.cuda.make_graphed_callables(images, (delta_n, sources_um, gain), num_warmup_iters=warmup_iters)
