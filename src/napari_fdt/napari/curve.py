"""The training and validation error of a run against iteration, as polylines for a small plot (no Qt here).

:class:`ErrorCurve` collects ``(global iteration, train error, validation error)`` from snapshots and maps them
to pixel coordinates of a plot ``width × height`` px: iteration linear from 0 to the run's total, error on a log
scale between the smallest and largest value seen (a decade at least), y growing downwards as on a screen.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

__all__ = ["ErrorCurve"]


@dataclass
class ErrorCurve:
    """Points of one run. ``total_iterations``: the x range; ``margin_px``: blank border inside the plot."""

    total_iterations: int = 1
    margin_px: int = 4
    train: list[tuple[int, float]] = field(default_factory=list)
    validation: list[tuple[int, float]] = field(default_factory=list)

    def reset(self, total_iterations: int) -> None:
        """Start a new run of ``total_iterations`` iterations."""
        self.total_iterations = max(1, int(total_iterations))
        self.train.clear()
        self.validation.clear()

    def add(self, snapshot: Any) -> None:
        """Record a :class:`~napari_fdt.recon.run.solver.Snapshot`'s errors (those that are None or not finite are skipped).

        A snapshot before the last point's iteration means the run went back (a stage run again from its start,
        e.g. with model parts the validation error chose): the points from there on are replaced, not doubled."""
        it = int(snapshot.global_iteration)
        for series, value in ((self.train, snapshot.train_error), (self.validation, snapshot.validation_error)):
            if series and series[-1][0] > it:
                while series and series[-1][0] >= it:
                    series.pop()
            if value is not None and math.isfinite(value) and value > 0:
                series.append((it, float(value)))

    def error_range(self) -> tuple[float, float]:
        """(low, high) of the log axis: the values seen, widened to one decade at least."""
        values = [v for _, v in self.train + self.validation]
        if not values:
            return 0.01, 1.0
        lo, hi = min(values), max(values)
        mid = math.sqrt(lo * hi)
        if hi / lo < 10.0:
            lo, hi = mid / math.sqrt(10.0), mid * math.sqrt(10.0)
        return lo, hi

    def polylines(self, width: int, height: int) -> dict[str, list[tuple[float, float]]]:
        """``{"train": [(x, y), …], "validation": […]}`` in pixels of a ``width × height`` plot."""
        lo, hi = self.error_range()
        m = self.margin_px
        w, h = max(1, width - 2 * m), max(1, height - 2 * m)
        span = math.log(hi / lo)

        def to_px(it: int, v: float) -> tuple[float, float]:
            x = m + w * min(1.0, it / self.total_iterations)
            y = m + h * (1.0 - math.log(v / lo) / span)
            return x, min(max(y, m), m + h)

        return {"train": [to_px(i, v) for i, v in self.train], "validation": [to_px(i, v) for i, v in self.validation]}

    def caption(self) -> str:
        """The latest values, e.g. ``"train 0.031, validation 0.034 (best 0.033 at 250)"``."""
        parts = []
        if self.train:
            parts.append(f"train {self.train[-1][1]:.3g}")
        if self.validation:
            best_it, best = min(self.validation, key=lambda p: p[1])
            parts.append(f"validation {self.validation[-1][1]:.3g} (best {best:.3g} at {best_it})")
        return ", ".join(parts) or "no errors yet"
