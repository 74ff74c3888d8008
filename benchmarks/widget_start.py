"""Seconds from the reconstruction widget's click to the run's first iteration on the bundled sample (issue 48, item 2).

    xvfb-run -a python -m benchmarks run widget_start [--repeats 3] [--write]

A napari viewer (not shown) opens ``sample_data/letters`` with the plugin's reader, docks *FDT reconstruction* (the
defaults, device cpu) and clicks *Reconstruct*, ``--repeats`` times in the same viewer, cancelling each run at its
first snapshot. Per click: the seconds to the computation process's connection (its start and imports), to the job's
"started" update (the solver built) and to the first snapshot (the pupil's pilot's first steps; the row says after
how many). ``--write`` appends the rows to ``benchmarks/results/widget_start_cpu.jsonl``. Nothing is asserted; this
reports.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args(argv)

    t_process = time.perf_counter()
    import napari
    from qtpy.QtWidgets import QApplication

    from napari_fdt.napari.jobs import remote_job
    from napari_fdt.napari.widgets.widget_reconstruction import ReconstructionWidget

    imports_s = time.perf_counter() - t_process
    viewer = napari.Viewer(show=False)
    viewer.open(str(ROOT / "sample_data" / "letters"), plugin="napari-fdt")
    widget = ReconstructionWidget(viewer)
    viewer.window.add_dock_widget(widget, name="FDT reconstruction")
    widget.device.value = "cpu"
    marks: dict[str, float] = {}
    start = remote_job._Child.start.__func__

    def timed_start(cls, *a, **k):
        child = start(cls, *a, **k)
        marks.setdefault("connected", time.perf_counter())
        return child

    remote_job._Child.start = classmethod(timed_start)
    on_update = widget._on_update

    def timed_update(update) -> None:
        key = "started" if update.kind == "started" else "first_snapshot" if update.snapshot is not None else None
        if key:
            marks.setdefault(key, time.perf_counter())
        if key == "first_snapshot":
            marks.setdefault("at_iteration", int(update.snapshot.plan_iteration))
        on_update(update)

    widget._on_update = timed_update
    app = QApplication.instance()
    rows = []
    for _ in range(args.repeats):
        marks.clear()
        t0 = time.perf_counter()
        widget.run_button.clicked.emit()
        while "first_snapshot" not in marks and time.perf_counter() - t0 < 120:
            app.processEvents()
            time.sleep(0.002)
        widget.cancel()
        while (widget.running or widget._worker is not None) and time.perf_counter() - t0 < 300:
            app.processEvents()
            time.sleep(0.01)
        row = {k: round(marks[k] - t0, 3) for k in ("connected", "started", "first_snapshot") if k in marks}
        row["first_snapshot_after_iterations"] = marks.get("at_iteration")
        rows.append(row)
        print(row, flush=True)
    print({"median_first_snapshot_s": statistics.median(r["first_snapshot"] for r in rows),
           "viewer_process_imports_s": round(imports_s, 3)})
    if args.write:
        from benchmarks._results import append_row, results_file

        for r in rows:
            append_row(results_file("widget_start", "cpu"), {**r, "entry": "widget click", "repeats": args.repeats})
    viewer.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
