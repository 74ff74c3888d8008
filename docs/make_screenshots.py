"""Take the screenshots of docs/napari.md from the real plugin (so they stay current).

    xvfb-run -a -s "-screen 0 1600x1000x24" .venv/bin/python docs/make_screenshots.py

Opens the bundled letters sample in a 1600×1000 napari window, docks both widgets side by side (one above
the other, as napari docks them), shows the sources, masks and a forward preview, runs a short
reconstruction (stages 4x60, 2x60, 1x60: about 30 s on 2 CPU cores), and saves PNGs under docs/images/:
the whole window with both widgets, each widget, the viewer during the run, the RI volume in 3D, and the
predicted-versus-measured image. Needs napari with a Qt binding and an X display (Xvfb is fine).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import napari
import numpy as np
from PIL import Image
from qtpy.QtGui import QImage
from qtpy.QtWidgets import QApplication, QWidget

from napari_fdt.napari.widgets.widget_acquisition import AcquisitionWidget
from napari_fdt.napari.widgets.widget_reconstruction import ReconstructionWidget

OUT = Path(__file__).resolve().parent / "images"
WINDOW: list = []  # napari's main window (a Qt widget), found through a docked widget
STAGES = "4x60, 2x60, 1x60"


def pump(seconds: float = 0.2) -> None:
    """Let Qt draw (and the worker's updates arrive) for ``seconds``."""
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        QApplication.processEvents()
        time.sleep(0.01)


def save_png(rgba: np.ndarray, name: str, width: int, crop: bool = False) -> None:
    """Save an RGBA array as a small PNG: cropped to its content (``crop``), at most ``width`` px, 256 colours."""
    img = rgba[..., :3]
    if crop:
        lit = np.argwhere(img.max(axis=2) > 12)
        if lit.size:
            (y0, x0), (y1, x1) = lit.min(axis=0), lit.max(axis=0)
            m = 12
            img = img[max(0, y0 - m): y1 + m, max(0, x0 - m): x1 + m]
    im = Image.fromarray(np.ascontiguousarray(img))
    if im.width > width:
        im = im.resize((width, round(im.height * width / im.width)), Image.LANCZOS)
    im.quantize(256, method=Image.Quantize.MEDIANCUT).save(OUT / name, optimize=True)
    print("wrote", OUT / name)


def grab(widget, name: str, width: int = 400) -> None:
    """Save a widget as it is drawn."""
    qimg = widget.native.grab().toImage().convertToFormat(QImage.Format.Format_RGBA8888)
    w, h = qimg.width(), qimg.height()
    ptr = qimg.constBits()
    ptr.setsize(qimg.sizeInBytes())
    arr = np.frombuffer(ptr, np.uint8).reshape(h, qimg.bytesPerLine())[:, : 4 * w].reshape(h, w, 4).copy()
    save_png(arr, name, width)


def grab_floating(widget, dock, name: str, height: int = 980) -> None:
    """Save a widget whole: its dock floated for a moment at ``height`` px (docked, its sections scroll)."""
    dock.setFloating(True)
    dock.resize(420, height)
    pump(0.5)
    grab(widget, name)
    dock.setFloating(False)
    pump(0.3)


def shot(viewer, name: str, width: int, canvas_only: bool = True, crop: bool = False) -> None:
    """Save the canvas (or the whole window); cropped shots leave the scale bar out."""
    for toast in WINDOW[0].findChildren(QWidget):
        if type(toast).__name__ == "NapariQtNotification":
            toast.close()  # third-party deprecation toasts (e.g. about Qt5) are not part of the tutorial
    pump(0.2)
    viewer.scale_bar.visible = not crop
    save_png(viewer.screenshot(canvas_only=canvas_only, flash=False), name, width, crop)
    viewer.scale_bar.visible = True


def wait_tasks(widget, timeout_s: float = 120.0) -> None:
    """Until the widget's background actions (previews, comparison) have shown their result."""
    deadline = time.perf_counter() + timeout_s
    while not widget.tasks.idle and time.perf_counter() < deadline:
        pump(0.1)


def view_3d(viewer, angles, center, zoom) -> None:
    cam = viewer.camera
    cam.angles = angles
    cam.center = center
    cam.zoom = zoom
    pump(0.5)


def main() -> int:
    OUT.mkdir(parents=True, exist_ok=True)
    viewer = napari.Viewer(title="napari-fdt")
    viewer.open_sample("napari-fdt", "letters")
    acq_layer = viewer.layers["letters"]
    viewer.scale_bar.visible = True

    acq_w = AcquisitionWidget(viewer)
    acq_dock = viewer.window.add_dock_widget(acq_w, name="FDT acquisition", area="right")
    rec_w = ReconstructionWidget(viewer)
    rec_dock = viewer.window.add_dock_widget(rec_w, name="FDT reconstruction", area="right")
    WINDOW.append(rec_w.native.window())
    WINDOW[0].resize(1600, 1000)
    pump(0.5)

    # Acquisition: sources from the file, masks, a forward preview of image 27
    acq_w.sources_from_file()
    rec_w.preview_masks()
    acq_w.image_index.value = 27
    acq_w.preview_image()
    wait_tasks(acq_w)
    wait_tasks(rec_w)
    pump(0.5)
    grab_floating(acq_w, acq_dock, "acquisition_widget.png")
    viewer.layers.selection = {acq_layer}
    viewer.dims.set_point(0, 0.0)  # image 0 (the image axis): a corner source, its disc edge inside the image
    for layer in viewer.layers:
        layer.visible = layer.name in ("letters", "letters masks")
    viewer.reset_view()
    pump(0.3)
    shot(viewer, "masks.png", 320, crop=True)
    for layer in viewer.layers:
        layer.visible = layer.name in ("letters", "letters sources")
    pump(0.3)
    shot(viewer, "docked.png", 1000, canvas_only=False)

    # Reconstruction: stream the RI volume
    for layer in viewer.layers:
        layer.visible = False
    rec_w.stages.value = STAGES
    rec_w.validation_fraction.value = 0.1  # shows the validation curve (orange) beside the training one
    rec_w.device.value = "cpu"
    rec_w.start()
    deadline = time.perf_counter() + 1800  # a busy machine can be 10× slower than the 30 s quoted above
    while rec_w._ri_layer is None and rec_w.running and time.perf_counter() < deadline:
        pump(0.1)  # the RI layer appears with the run's first volume (after the TV pilot)
    ri = rec_w._ri_layer
    ri.rendering = "mip"
    viewer.dims.ndisplay = 3
    viewer.layers["letters sources"].visible = True
    view_3d(viewer, (-25, 35, 130), (-14, 0, 0), 9)
    calibrated = "letters sources calibrated #1"
    while "stage 3/3" not in rec_w.status.value and time.perf_counter() < deadline:
        pump(0.1)
    pump(1.0)
    shot(viewer, "run_in_progress.png", 1000, canvas_only=False)
    while rec_w.running and time.perf_counter() < deadline:
        pump(0.2)
    pump(0.5)
    if rec_w.feedback.last_error:
        print("reconstruction failed:", rec_w.feedback.last_error, file=sys.stderr)
        return 1
    grab_floating(rec_w, rec_dock, "reconstruction_widget.png")

    # The RI volume in 3D: alone, then with the sources 40 µm below it
    ri.contrast_limits = (1.33, 1.38)
    for name in ("letters sources", calibrated):
        viewer.layers[name].visible = False
    view_3d(viewer, (-30, 45, 160), (8, 0, 0), 14)
    shot(viewer, "ri_3d.png", 480, crop=True)
    viewer.layers[calibrated].visible = True
    view_3d(viewer, (-25, 35, 130), (-14, 0, 0), 9)
    shot(viewer, "geometry_3d.png", 360, crop=True)
    viewer.layers[calibrated].visible = False
    viewer.dims.ndisplay = 2
    viewer.dims.set_point(0, 0.0)
    pump(0.3)

    # Predicted versus measured image 27
    rec_w.show_comparison(27)
    wait_tasks(rec_w)
    for layer in viewer.layers:
        layer.visible = layer.name.endswith("predicted | measured")
    viewer.reset_view()
    pump(0.5)
    shot(viewer, "predicted_vs_measured.png", 440, crop=True)
    print("sizes (KB):", {p.name: round(p.stat().st_size / 1024) for p in sorted(OUT.glob("*.png"))})
    viewer.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
