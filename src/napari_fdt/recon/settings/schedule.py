"""Step-size schedules of the solver's optimisers (pure functions of the iteration; no state)."""

from __future__ import annotations

import math

__all__ = ["final_step_scale"]


def final_step_scale(iteration: int, iterations: int, final_ratio: float) -> float:
    """Factor on the RI step at ``iteration`` (1 … ``iterations``) of the finest stage: a half cosine from 1 at the
    first iteration to ``final_ratio`` at the last, ½(1 + cos(π·t))·(1 − r) + r with t = (iteration − 1)/(iterations − 1).

    ``final_ratio`` 1 is the constant step. With a stochastic batch of images per iteration the volume moves by about
    the step each iteration to the end; a falling step lets the last iterates settle instead of ending wherever the
    last batches pushed them.
    """
    if final_ratio >= 1.0 or iterations <= 1:
        return 1.0
    t = (min(max(iteration, 1), iterations) - 1) / (iterations - 1)
    return final_ratio + (1.0 - final_ratio) * 0.5 * (1.0 + math.cos(math.pi * t))
