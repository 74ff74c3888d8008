"""The time left of a run: its :class:`~napari_fdt.recon.loop.plan.Plan` corrected by the times the run measures."""

from __future__ import annotations

from napari_fdt.recon.loop.plan import Plan

__all__ = ["Pace"]


class Pace:
    """Time left from a :class:`Plan` and the times a run measures.

    :meth:`observe` takes each snapshot's phase index, the iterations done along the plan and the run's elapsed
    seconds. A phase's first interval (from the previous snapshot to its first) holds its set-up (building the stage's
    model) and is kept apart from its steady intervals. The steady seconds measured, over the plan's prediction for the
    same iterations, is the correction applied to the phases ahead; the current phase's rest goes at its own steady pace
    once it has one; each phase ahead adds the mean set-up time measured.
    """

    def __init__(self, plan: Plan) -> None:
        self.plan = plan
        self._last: tuple[int, int, float] | None = None  # (phase, done, elapsed)
        #: phase → [iterations, seconds] of its first interval, and of its steady intervals
        self._first: dict[int, list[float]] = {}
        self._steady: dict[int, list[float]] = {}

    def observe(self, phase: int, done: int, elapsed_s: float) -> None:
        """``done`` iterations along the plan after ``elapsed_s`` seconds of the run, in phase ``phase``."""
        if self._last is None:
            prev_done, prev_t = self.plan.iterations_before(phase), 0.0
        else:
            prev_done, prev_t = self._last[1], self._last[2]
        acc = self._first if phase not in self._first else self._steady
        n, s = acc.setdefault(phase, [0.0, 0.0])
        acc[phase] = [n + max(0, int(done) - prev_done), s + max(0.0, float(elapsed_s) - prev_t)]
        self._last = (phase, int(done), float(elapsed_s))

    def _predicted(self, phase: int, iterations: float) -> float:
        return iterations * self.plan.phases[phase].seconds_per_iteration

    def correction(self) -> float:
        """Measured over predicted seconds of the steady intervals seen (of the first intervals while there are none;
        1 before any)."""
        acc = self._steady if any(n > 0 for n, _ in self._steady.values()) else self._first
        seen = sum(s for _, s in acc.values())
        predicted = sum(self._predicted(i, n) for i, (n, _) in acc.items())
        return seen / predicted if predicted > 0 and seen > 0 else 1.0

    def setup_seconds(self) -> float:
        """The mean set-up time of a phase: the excess of its first interval over its steady pace."""
        extra = [max(0.0, first[1] - first[0] * self._steady[i][1] / self._steady[i][0])
                 for i, first in self._first.items() if i in self._steady and self._steady[i][0] > 0 and first[0] > 0]
        return sum(extra) / len(extra) if extra else 0.0

    def seconds_left(self) -> float:
        """Seconds to the end of the plan (its prediction before any observation)."""
        if self._last is None:
            return self.plan.predicted_s
        phase, done, _ = self._last
        ratio = self.correction()
        p = self.plan.phases[phase]
        n, s = self._steady.get(phase, (0, 0.0))
        per_it = s / n if n > 0 else p.seconds_per_iteration * ratio
        left_here = max(0, self.plan.iterations_before(phase) + p.iterations - done)
        ahead = self.plan.phases[phase + 1:]
        test_here = ratio * p.test_s if left_here > 0 else 0.0  # the tests at this phase's end (once its iterations are done, under way)
        return left_here * per_it + test_here + ratio * sum(q.predicted_s for q in ahead) + len(ahead) * self.setup_seconds()

    def measured_seconds(self) -> list[float | None]:
        """Each phase's measured seconds, set-up included (None for a phase not reached)."""
        return [None if i not in self._first else self._first[i][1] + self._steady.get(i, (0, 0.0))[1]
                for i in range(len(self.plan.phases))]
