"""What ``fdt reconstruct`` shows while it runs: the progress bar along the run's plan (a line per refresh where stderr
is not a terminal), and the warning before a CPU run predicted to take long."""

from __future__ import annotations

import sys
import warnings

from napari_fdt.errors import FDTWarning

__all__ = ["LONG_CPU_RUN_S"]


class _LineStream:
    """A text stream for tqdm where stderr is not a terminal (SLURM logs, pipes): each refresh becomes one plain
    line, without the carriage returns a terminal needs to redraw the bar in place."""

    def __init__(self, stream) -> None:
        self.stream = stream

    def write(self, text: str) -> int:
        line = text.replace("\r", "").strip()
        if line:
            self.stream.write(line + "\n")
        return len(text)

    def flush(self) -> None:
        self.stream.flush()


def _progress_bar(total: int, *, disable: bool, stream=None):
    """A tqdm bar on stderr: redrawn in place on a terminal; elsewhere ASCII, one line every 30 s (``TQDM_MININTERVAL``
    overrides) and at each stage's end, so a batch log stays readable."""
    from tqdm import tqdm

    stream = sys.stderr if stream is None else stream
    tty = hasattr(stream, "isatty") and stream.isatty()
    if tty:
        return tqdm(total=total, unit="it", file=stream, dynamic_ncols=True, disable=disable, leave=True)
    return tqdm(total=total, unit="it", file=_LineStream(stream), ascii=True, ncols=110, mininterval=30.0, disable=disable)


def _show_progress(bar, snap) -> None:
    """Advance the bar to a snapshot: the plan's phase in words, loss, validation error and the solver's time-left.

    The bar counts the iterations of the whole plan (:mod:`napari_fdt.recon.loop.plan`: the stages, the trials of the TV
    weights, and the stages run again with kept model parts), so it never starts again; it grows when a choice of
    model parts appends the stages run again. A line is written after each TV weight tried and each stage's end.
    """
    weights = snap.tv_weights
    bar.set_description(snap.phase_name + (f", tried xy {weights[0]:g}" if weights is not None else ""), refresh=False)
    post = {}
    loss = snap.losses.get("total")
    if loss is not None:
        post["loss"] = f"{loss:.4g}"
    if snap.validation_error is not None:
        post["val"] = f"{snap.validation_error:.4f}"
    post["left"] = f"{snap.eta_s:.0f}s"
    most = getattr(snap, "eta_up_to_s", None)  # the choices still open could add this much
    if most is not None:
        post["up to"] = f"{most:.0f}s"
    bar.set_postfix(post, refresh=False)
    if bar.total != snap.plan_iterations:
        bar.total = snap.plan_iterations
    step = snap.plan_iteration - bar.n
    if step > 0:
        bar.update(step)
    if bar.disable:
        return
    if weights is not None:
        val = f"validation error {snap.validation_error:.4f}" if snap.validation_error is not None else "no validation error"
        bar.write(f"choosing the TV weight: tried xy {weights[0]:g}, z {weights[1]:g}: {val}", file=bar.fp)
    elif snap.stage_complete:
        bar.write(f"{snap.phase_name} complete" + (f", loss {loss:.4g}" if loss is not None else ""), file=bar.fp)


#: A CPU run predicted to take longer than this (seconds) gets a warning that names the GPU option.
LONG_CPU_RUN_S = 1800.0


def _warn_about_a_long_cpu_run(plan, device_type: str) -> None:
    """Warn (FDTWarning) when a CPU run's plan predicts more than :data:`LONG_CPU_RUN_S`, or up to more where the data
    choose (its range's top, :attr:`~napari_fdt.recon.loop.plan.Plan.most_s`)."""
    if device_type != "cpu":
        return
    if plan.predicted_s > LONG_CPU_RUN_S:
        what = f"predicted to take about {plan.predicted_s / 3600:.1f} h"
    elif plan.most_s is not None and plan.most_s > LONG_CPU_RUN_S:
        what = (f"predicted to take about {plan.predicted_s / 60:.0f} min, and up to {plan.most_s / 3600:.1f} h where the "
                "data ask for the costliest model parts")
    else:
        return
    warnings.warn(f"device: this CPU run is {what} (the plan above); on a machine with an NVIDIA GPU, --device cuda runs "
                  "it far faster (docs/install.md: the CUDA build of torch), or give fewer or shorter stages", FDTWarning,
                  stacklevel=2)
