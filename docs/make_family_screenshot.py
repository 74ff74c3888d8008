"""Take docs/napari.md's screenshot of the smoothing family from the real plugin (1600×1000 window):

    xvfb-run -a -s "-screen 0 1600x1000x24" .venv/bin/python docs/make_family_screenshot.py

Opens the bundled letters sample, docks *FDT smoothing family*, runs the family with short stages (4x60, 2x60, 1x60
per member: about 2 min on 2 CPU cores), moves the slider to a member other than the pick (what a user comparing them
sees) and saves docs/images/family.png (the whole window) and family_widget.png (the widget).
"""

from __future__ import annotations

import sys
import time

import napari
from make_screenshots import OUT, WINDOW, grab, pump, shot

from napari_fdt.napari.settings import parse_stages
from napari_fdt.napari.widgets.widget_family import FamilyWidget
from napari_fdt.recon.settings.config import SolverConfig


def main() -> int:
    OUT.mkdir(parents=True, exist_ok=True)
    viewer = napari.Viewer(title="napari-fdt")
    viewer.open_sample("napari-fdt", "letters")
    viewer.scale_bar.visible = True
    w = FamilyWidget(viewer)
    viewer.window.add_dock_widget(w, name="FDT smoothing family", area="right")
    WINDOW.append(w.native.window())
    WINDOW[0].resize(1600, 1000)
    pump(0.5)
    w.config = SolverConfig(stages=parse_stages("4x60, 2x60, 1x60"))
    w.device.value = "cpu"
    w.start()
    deadline = time.perf_counter() + 900
    while (w.running or w.family is None) and time.perf_counter() < deadline:
        pump(0.2)
    if w.family is None:
        print("the family did not finish", file=sys.stderr)
        return 1
    for layer in viewer.layers:
        layer.visible = "member shown" in layer.name
    viewer.dims.ndisplay = 2
    viewer.dims.set_point(0, viewer.layers[-1].translate[0] + 4 * viewer.layers[-1].scale[0])
    w.smoothing.value = (w.family["pick"] + 1) % len(w.members)
    viewer.reset_view()
    pump(0.5)
    shot(viewer, "family.png", 1600, canvas_only=False)
    grab(w, "family_widget.png")
    viewer.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
