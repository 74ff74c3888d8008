"""The first run as a new user makes it, in a fresh interpreter (run by tests/test_first_gui_run.py under Xvfb).

napari shown (its OpenGL driver loaded: with Mesa's, Triton must never be imported in this process), both widgets
docked through the plugin manifest, the letters sample opened, Reconstruct clicked with the defaults, then wait for
the end. Prints one JSON line of what a user would see; ``--screenshot PATH`` saves the window (1600×1000).
"""

from __future__ import annotations

import argparse
import faulthandler
import json
import sys
import time

import numpy as np

faulthandler.enable()
if "--debug-hang" in sys.argv:
    sys.argv.remove("--debug-hang")
    faulthandler.dump_traceback_later(100, exit=True)


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--screenshot", default=None)
    parser.add_argument("--screenshot-3d", default=None)
    parser.add_argument("--timeout-s", type=float, default=900.0)
    parser.add_argument("--stages", default=None, help="instead of the default stages (quick looks at the layout)")
    args = parser.parse_args()

    import napari
    from qtpy.QtWidgets import QApplication

    viewer = napari.Viewer(show=True)
    viewer.window.resize(1600, 1000)
    app = QApplication.instance()

    def spin(seconds: float) -> None:
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            app.processEvents()
            time.sleep(0.01)

    _, acquisition = viewer.window.add_plugin_dock_widget("napari-fdt", "FDT acquisition")
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdt", "FDT reconstruction")
    viewer.open_sample("napari-fdt", "letters")
    spin(1.0)  # the canvas draws: the OpenGL driver is loaded now
    if args.stages:
        widget.stages.value = args.stages
    t0 = time.monotonic()
    widget.run_button.native.click()
    statuses = []
    while (widget.running or widget._worker is not None) and time.monotonic() - t0 < args.timeout_s:
        spin(0.2)
        if not statuses or statuses[-1] != widget.status.value:
            statuses.append(widget.status.value)
            print(f"{time.monotonic() - t0:7.1f} s  {widget.progress.value}/{widget.progress.max}  {widget.status.value}",
                  file=sys.stderr, flush=True)
    spin(0.5)
    ri = widget._ri_layer
    z_axis = viewer.dims.ndim - 3
    z = float(viewer.dims.point[z_axis])
    out = {
        "seconds": time.monotonic() - t0,
        "running": widget.running,
        "status": widget.status.value,
        "results": widget.results.value,
        "error": widget.feedback.last_error,
        "ri_layer": None if ri is None else ri.name,
        "selected": None if viewer.layers.selection.active is None else viewer.layers.selection.active.name,
        "z_um": z,
        "ri_z_um": None if ri is None else [float(ri.translate[0]), float(ri.translate[0] + (ri.data.shape[0] - 1) * ri.scale[0])],
        "ri_slice": None if ri is None else int(round((z - ri.translate[0]) / ri.scale[0])),
        "contrast_limits": None if ri is None else [float(c) for c in ri.contrast_limits],
        "ri_range": None if ri is None else [float(ri.data.min()), float(ri.data.max())],
        # how much structure the truth has on each slice (mean |Δn|): the slice shown should hold some
        "truth_slice_content": [float(v) for v in np.abs(viewer.layers["letters ground truth RI"].data - 1.33).mean(axis=(1, 2))],
        "triton_imported": "triton" in sys.modules,
        "dynamo_imported": "torch._dynamo" in sys.modules,
        "first_statuses": statuses[:3],
        "layers": [layer.name for layer in viewer.layers],
    }
    if args.screenshot:
        viewer.screenshot(args.screenshot, canvas_only=False)
    if args.screenshot_3d:
        viewer.dims.ndisplay = 3
        spin(1.0)
        from napari_fdt.napari.result_view import camera

        out["camera_angles_3d"] = [float(a) for a in camera(viewer).angles]
        viewer.screenshot(args.screenshot_3d, canvas_only=False)
    print(json.dumps(out))
    viewer.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
