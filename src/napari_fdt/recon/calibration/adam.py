"""The run's Adam: torch's algorithm, state and state dict, stepped without importing torch's compiler.

torch.optim imports ``torch._dynamo`` (1.1 s on a 2-core CPU, 2026-11-27, against 1.4 s for all of ``import napari_fdt``)
the first time an optimiser adds a parameter group, zeroes its gradients, reads or loads its state, or steps: to keep
those methods out of compiled graphs (``torch._disable_dynamo``, and a ``torch._dynamo.graph_break()`` in every
``step``). This package compiles nothing that calls an optimiser, so that import was a cold start's single largest
cost. Here:

- :class:`Adam` is ``torch.optim.Adam`` whose :meth:`~Adam.step` calls torch's own implementation (the single-tensor
  loop, or the ``foreach`` one where torch would choose it: on CUDA) directly, under ``torch.no_grad``; its state and
  state dict are torch's (checkpoints unchanged), and its arithmetic is the same op for op (``tests/test_adam.py``).
- :func:`optimisers_without_compiler` gives the wrapped methods of every ``torch.optim.Optimizer`` (this package's
  :class:`~napari_fdt.recon.calibration.calibration.RowAdam` too) their plain form as the compiler-excluded one that
  ``torch._disable_dynamo`` caches, while ``torch._dynamo`` is not imported; where it is (a caller's compiled code),
  nothing changes. A process that imports the package first and compiles its own code later would have dynamo trace
  these four methods where it skipped them (they are plain Python over tensors' ``grad`` and dicts).

Both reach into torch's private functions (``torch.optim.adam._single_tensor_adam`` and ``_multi_tensor_adam``,
``torch.optim.optimizer._default_to_fused_or_foreach``, the ``__dynamo_disable`` cache of ``torch._compile``), checked
for at import: under a torch without them, :class:`Adam` steps as ``torch.optim.Adam`` does and nothing is changed.
"""

from __future__ import annotations

import importlib
import sys
from typing import Any

import torch

__all__ = ["Adam", "optimisers_without_compiler"]

#: Methods of ``torch.optim.Optimizer`` wrapped in ``torch._disable_dynamo`` (torch 2.13).
_WRAPPED_METHODS = ("add_param_group", "zero_grad", "state_dict", "load_state_dict")


def _torch_adam() -> tuple[Any, Any, Any] | None:
    """torch's single-tensor and foreach Adam and its choice between them, or None where this torch lacks them."""
    try:
        functional = importlib.import_module("torch.optim.adam")  # (torch.optim deletes its submodules' names)
        optimizer = importlib.import_module("torch.optim.optimizer")
        return functional._single_tensor_adam, functional._multi_tensor_adam, optimizer._default_to_fused_or_foreach
    except (ImportError, AttributeError):
        return None


_IMPLEMENTATION = _torch_adam()


def optimisers_without_compiler() -> None:
    """While ``torch._dynamo`` is not imported, let ``torch.optim.Optimizer``'s wrapped methods run as they are, without
    importing it (the module's docstring). Idempotent."""
    if "torch._dynamo" in sys.modules:
        return
    for name in _WRAPPED_METHODS:
        plain = getattr(getattr(torch.optim.Optimizer, name, None), "__wrapped__", None)
        if plain is not None and getattr(plain, "__dynamo_disable", None) is None:
            setattr(plain, "__dynamo_disable", plain)


optimisers_without_compiler()


class Adam(torch.optim.Adam):
    """``torch.optim.Adam`` (same arguments, state and state dict) stepped without the compiler's import."""

    def _plain(self) -> bool:
        """Whether every group is plain Adam (not fused, capturable, differentiable, amsgrad), as this package makes it."""
        return _IMPLEMENTATION is not None and not any(
            g["fused"] or g["capturable"] or g["differentiable"] or g["amsgrad"] for g in self.param_groups)

    @torch.no_grad()
    def step(self, closure=None):  # noqa: D102 (torch's signature)
        if closure is not None or not self._plain():
            return super().step(closure)
        single, multi, default_foreach = _IMPLEMENTATION
        for group in self.param_groups:
            params, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps = [], [], [], [], [], []
            has_complex = self._init_group(group, params, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps)
            foreach = group["foreach"]
            if foreach is None:  # torch's choice: foreach where every tensor is on CUDA (and the like), not on the CPU
                _, foreach = default_foreach(params, False, use_fused=False)
            if foreach and isinstance(group["lr"], torch.Tensor):
                foreach = False
            beta1, beta2 = group["betas"]
            (multi if foreach else single)(
                params, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps, grad_scale=None, found_inf=None,
                amsgrad=False, has_complex=has_complex, beta1=beta1, beta2=beta2, lr=group["lr"],
                weight_decay=group["weight_decay"], eps=group["eps"], maximize=group["maximize"], capturable=False,
                differentiable=False, decoupled_weight_decay=group["decoupled_weight_decay"])
        return None
