"""The order in which the solver visits the images: seeded random permutations, cut into batches."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

__all__ = ["BatchOrder"]


class BatchOrder:
    """Batches of image indices: one random permutation of the N images after another (a seeded generator),
    cut into consecutive batches, so that every image is visited once per pass whatever the batch size.

    ``n_images``: N; ``seed``: of the generator; ``device``: where the index tensors go.
    """

    def __init__(self, n_images: int, seed: int, device: torch.device) -> None:
        self.n_images = n_images
        self.device = device
        self.generator = torch.Generator().manual_seed(seed)
        self.order: list[int] = []

    def next(self, batch_size: int) -> torch.Tensor:
        """The next ``min(batch_size, N)`` indices, (B,) int64 on the device."""
        return self.to_device(self.next_host(batch_size))

    def next_host(self, batch_size: int) -> np.ndarray:
        """The next ``min(batch_size, N)`` indices, (B,) int64 in host memory (numpy): what the solver decides about a
        batch (which of its images are held out, their order) it decides on these, without waiting for the device."""
        n = self.n_images
        b = min(batch_size, n)
        while len(self.order) < b:
            self.order.extend(torch.randperm(n, generator=self.generator).tolist())
        idx, self.order = self.order[:b], self.order[b:]
        return np.asarray(idx, dtype=np.int64)

    def to_device(self, indices: np.ndarray) -> torch.Tensor:
        """Host ``indices`` as an int64 tensor on the device; on CUDA pinned and non-blocking: no wait for the GPU's
        queue to drain."""
        t = torch.from_numpy(np.ascontiguousarray(indices, dtype=np.int64))
        if self.device.type == "cuda":
            return t.pin_memory().to(self.device, non_blocking=True)
        return t.to(self.device)

    def state_dict(self) -> dict[str, Any]:
        """The generator's state (``batch_gen``) and the rest of the current pass (``order``)."""
        return {"batch_gen": self.generator.get_state(), "order": list(self.order)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from :meth:`state_dict`."""
        self.generator.set_state(state["batch_gen"])
        self.order = list(state["order"])
