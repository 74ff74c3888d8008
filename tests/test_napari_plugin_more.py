"""The napari plugin in a real (hidden) viewer, continued: background actions off the GUI thread, corrupted input,
settings generated from the schema, the error curve, nothing a user made is lost, the hand-off to the command line,
the screen. Set-up: tests/napari_helpers.py."""

from __future__ import annotations

import dataclasses
import json
import sys

import numpy as np
import pytest

from benchmarks.scenes import tiny_scene
from tests.napari_helpers import (
    META_ACQUISITION,
    META_KIND,
    PLUGIN,
    Acquisition,
    AcquisitionWidget,
    FDTWarning,
    Optics,
    Points,
    ReconstructionWidget,
    SolverConfig,
    _docked,
    _open,
    _settings,
    _wait_done,
    _wait_tasks,
    read_volume_tiff,
    write_acquisition,
)

# -- background actions: off the GUI thread, one result, errors shown ---------------------------------------


@pytest.fixture()
def held_fit(monkeypatch):
    """``initial_sources`` that waits for ``release`` before fitting, and records the thread it ran in."""
    import threading

    import napari_fdt.recon.calibration.source_fit as source_fit

    real = source_fit.initial_sources
    state = {"release": threading.Event(), "entered": threading.Event(), "threads": [], "real": real}

    def held(*args, **kwargs):
        state["threads"].append(threading.current_thread())
        state["entered"].set()
        assert state["release"].wait(timeout=60.0), "the test never released the fit"
        return real(*args, **kwargs)

    monkeypatch.setattr(source_fit, "initial_sources", held)
    return state


def test_fit_sources_runs_in_a_worker_and_the_gui_stays_live(make_napari_viewer, qtbot, tiny_dir, tiny_sim, held_fit,
                                                             notifications) -> None:
    import threading

    from qtpy.QtCore import QTimer

    viewer = make_napari_viewer()
    _open(viewer, tiny_dir)
    w = _docked(viewer, AcquisitionWidget(viewer))
    w.depth_um.value = "15"
    worker = w.fit_sources()
    # the call came back while the fit is held in its thread: the button is off, no result yet
    assert worker is not None and held_fit["entered"].wait(10.0)
    assert held_fit["threads"][0] is not threading.main_thread()
    assert not w.fit_button.enabled and w.tasks.is_running("fit sources")
    assert not any(isinstance(lay, Points) for lay in viewer.layers)
    assert "fitting the sources" in w.feedback.label.value
    # the GUI thread's event loop runs a timer while the fit is still held
    ticks = []
    timer = QTimer()
    timer.setInterval(10)
    timer.timeout.connect(lambda: ticks.append(w.tasks.is_running("fit sources")))
    timer.start()
    qtbot.waitUntil(lambda: len(ticks) >= 5, timeout=10_000)
    timer.stop()
    assert all(ticks)  # every tick came during the fit
    # a second press while it runs starts nothing
    assert w.fit_sources() is None
    held_fit["release"].set()
    _wait_tasks(qtbot, w)
    assert w.fit_button.enabled and w.feedback.last_error is None, w.feedback.label.value
    points = [lay for lay in viewer.layers if isinstance(lay, Points)]
    assert len(points) == 1 and points[0].data.shape == (9, 3)
    # the layer holds the fit of these images, as the core computes it in the GUI thread: points (z, y, x) = (−depth, y, x)
    # the fit's warning, raised in the worker thread, reached the user
    assert any("their x, y are unreliable" in m for m in notifications), notifications
    with pytest.warns(FDTWarning, match="unreliable"):
        expected, _ = held_fit["real"](tiny_sim.acquisition, depth_um=15.0, device="cpu")
    assert np.allclose(points[0].data, expected[:, [2, 1, 0]] * (-1, 1, 1), atol=1e-9)


def test_an_error_in_a_background_fit_is_shown_and_the_widget_stays_usable(make_napari_viewer, qtbot, tiny_dir, tiny_sim,
                                                                           notifications) -> None:
    from napari_fdt.napari.layers import acquisition_layer

    viewer = make_napari_viewer()
    good = _open(viewer, tiny_dir)
    blank = Acquisition(images=np.zeros_like(tiny_sim.acquisition.images), optics=tiny_sim.acquisition.optics)
    data, kwargs, _ = acquisition_layer(blank, name="blank")
    viewer.add_image(data, **kwargs)
    w = _docked(viewer, AcquisitionWidget(viewer))
    w.layer.value = viewer.layers["blank"]
    w.depth_um.value = "15"
    assert w.fit_sources() is not None  # the inputs are fine; the fit itself refuses blank images
    _wait_tasks(qtbot, w)
    assert w.feedback.last_error.startswith("images: 9 of 9 images are blank"), w.feedback.label.value
    assert any("images: 9 of 9 images are blank" in m for m in notifications)
    assert w.fit_button.enabled and not any(isinstance(lay, Points) for lay in viewer.layers)
    # still usable: the same button on the good acquisition gives its sources
    w.layer.value = good
    w.fit_sources()
    _wait_tasks(qtbot, w)
    assert w.feedback.last_error is None, w.feedback.label.value
    assert [lay.data.shape for lay in viewer.layers if isinstance(lay, Points)] == [(9, 3)]


def test_a_bug_in_a_preview_is_reported_with_its_type(make_napari_viewer, qtbot, tiny_dir, monkeypatch, notifications) -> None:
    import napari_fdt.napari.widgets.widget_results as wr  # the result and preview actions

    def broken(*args, **kwargs):
        raise RuntimeError("simulated failure")

    monkeypatch.setattr(wr, "mask_stack", broken)
    viewer = make_napari_viewer()
    _open(viewer, tiny_dir)
    w = _docked(viewer, AcquisitionWidget(viewer))
    r = _docked(viewer, ReconstructionWidget(viewer))
    w.sources_from_file()
    r.preview_masks()
    _wait_tasks(qtbot, r)
    assert r.feedback.last_error == "RuntimeError: simulated failure"
    assert any("simulated failure" in m for m in notifications)
    assert r.masks_button.enabled
    # the other previews still work
    w.preview_image()
    _wait_tasks(qtbot, w)
    assert w.feedback.last_error is None and viewer.layers[-1].metadata[META_KIND] == "preview"


def test_closing_the_viewer_stops_background_actions(make_napari_viewer, qtbot, tiny_dir, held_fit, monkeypatch) -> None:
    import threading

    import napari_fdt.napari.widgets.widget_acquisition as wa

    shown = []
    monkeypatch.setattr(wa, "set_sources", lambda *a, **k: shown.append(a))
    viewer = make_napari_viewer()
    _open(viewer, tiny_dir)
    w = _docked(viewer, AcquisitionWidget(viewer))
    w.depth_um.value = "15"
    w.fit_sources()
    assert held_fit["entered"].wait(10.0)
    task = w.tasks._tasks["fit sources"]
    threading.Timer(0.3, held_fit["release"].set).start()  # the fit can end only after close asked it to stop
    viewer.close()
    assert task.done.is_set()  # close waited for the thread
    qtbot.waitUntil(lambda: not task.worker.is_running, timeout=5000)
    qtbot.wait(50)
    assert shown == []  # its result was dropped, not added to a closed viewer


# -- corrupted input through napari: the core's message, and the plugin stays usable ------------------------


def _corrupt(folder, kind: str) -> str:
    """Corrupt an acquisition folder in place; returns the start of the message the core gives."""
    meta = json.loads((folder / "acquisition.json").read_text())
    if kind == "na":
        meta["na"] = 1.4
        (folder / "acquisition.json").write_text(json.dumps(meta))
        return "na: numerical aperture 1.4 is not below n_background 1.33"
    if kind == "sources":
        meta["sources_um"] = meta["sources_um"][:-1]
        (folder / "acquisition.json").write_text(json.dumps(meta))
        return "sources_um: holds 8 source positions but there are 9 images"
    if kind == "json":
        (folder / "acquisition.json").write_text(json.dumps(meta)[:-3])
        return "acquisition.json: is not valid JSON"
    raw = (folder / "images.tif").read_bytes()
    if kind == "truncated":
        (folder / "images.tif").write_bytes(raw[: len(raw) // 2])
        return "images: images.tif is not a readable TIFF"
    if kind == "png":
        (folder / "images.tif").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
        return "images: images.tif is not a readable TIFF: not a TIFF file"
    import tifffile

    images = tifffile.imread(folder / "images.tif").astype(np.float32)
    images[3, 5, 7] = np.nan
    tifffile.imwrite(folder / "images.tif", images)
    return "images: 1 non-finite pixels (NaN or Inf), first at image 3, row 5, col 7"


@pytest.mark.parametrize("kind", ["na", "sources", "json", "truncated", "png", "nan"])
def test_a_corrupted_acquisition_shows_the_core_message_and_napari_goes_on(make_napari_viewer, tiny_sim, tmp_path,
                                                                          kind) -> None:
    bad = write_acquisition(tiny_sim.acquisition, tmp_path / "bad")
    expected = _corrupt(bad, kind)
    viewer = make_napari_viewer()
    a = _docked(viewer, AcquisitionWidget(viewer))
    with pytest.raises(Exception) as exc:
        viewer.open(str(bad), plugin=PLUGIN)
    assert expected in str(exc.value) and "Traceback" not in str(exc.value)
    assert len(viewer.layers) == 0 and a.layer.value is None
    # still usable: a good acquisition opens, the widget takes it and acts on it
    good = write_acquisition(tiny_sim.acquisition, tmp_path / "good")
    layer = _open(viewer, good)
    assert a.layer.value is layer
    a.sources_from_file()
    assert a.feedback.last_error is None
    assert [lay.data.shape for lay in viewer.layers if isinstance(lay, Points)] == [(9, 3)]


def test_any_optics_typed_into_the_widget_is_applied_or_explained(make_napari_viewer, tiny_dir) -> None:
    """A small hypothesis run over the optics fields (including 0, negative and NA ≥ n_b): each value set is applied
    (and stored on the layer as typed) or refused with a message naming one field; valid optics apply afterwards."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    from napari_fdt.physics.optics import OPTICS_FIELDS

    viewer = make_napari_viewer()
    _open(viewer, tiny_dir)
    w = _docked(viewer, AcquisitionWidget(viewer))
    good = {name: getattr(w, name).value for name in OPTICS_FIELDS}
    from napari_fdt.napari.settings import OPTICS_LABELS

    values = st.fixed_dictionaries({
        "wavelength_um": st.sampled_from([0.0, 0.3, 0.635, 50.0]), "n_background": st.sampled_from([0.0, 0.5, 1.0, 1.33, 3.0]),
        "na": st.sampled_from([0.0, 0.5, 0.8, 1.33, 2.0]), "pixel_size_um": st.sampled_from([0.0, 0.01, 0.33, 5.0, 330.0]),
        "n_slices": st.sampled_from([0, 1, 4, 300]), "slice_spacing_um": st.sampled_from([0.0, 0.05, 2.0]),
        "image_plane_um": st.sampled_from([-1e4, 0.0, 3.0]),
    })

    @settings(max_examples=15, deadline=None, suppress_health_check=list(HealthCheck), database=None)
    @given(values)
    def check(typed: dict) -> None:
        for name, value in typed.items():
            getattr(w, name).value = f"{value:g}"
        w.apply_optics()
        if w.feedback.last_error is None:
            applied = w.layer.value.metadata[META_ACQUISITION].optics.to_dict()
            assert all(applied[k] == pytest.approx(v) for k, v in typed.items())
        else:  # refused, naming the field by the label the widget shows
            field = w.feedback.last_error.split(":")[0]
            assert field in OPTICS_LABELS.values(), w.feedback.last_error
            assert w.feedback.label.value.startswith(f"error: {field}: ")
        for name, value in good.items():
            getattr(w, name).value = value
        w.apply_optics()
        assert w.feedback.last_error is None, w.feedback.label.value

    check()


def test_settings_widgets_are_generated_from_the_schema(make_napari_viewer) -> None:
    """Bounds, defaults, choices and tooltips of the settings widgets are the schema's (no second declaration)."""
    from napari_fdt.napari.widgets.schema_widgets import schema_widget
    from napari_fdt.recon.settings.config import COARSE_MODELS, COHERENCE_MODELS
    from napari_fdt.schema import schema_fields

    viewer = make_napari_viewer()
    w = _docked(viewer, ReconstructionWidget(viewer))
    fields = schema_fields(SolverConfig)
    assert w.batch_size.min == 1 and w.snapshot_every.min == 1 and w.snapshot_every.value == SolverConfig().snapshot_every
    assert tuple(w.coarse_model.choices) == COARSE_MODELS and tuple(w.coherence.choices) == COHERENCE_MODELS
    assert w.mask_threshold.min == 0 and w.mask_threshold.max == 1
    # plain words in the label; the physics name, the field's name and the schema's description in the tooltip
    assert w.tv_xy_weight.label == "smoothing across (xy)"
    assert w.tv_xy_weight.tooltip == ("total variation (TV) weight, xy (tv_xy_weight): "
                                      + fields["tv_xy_weight"].description.replace("`", ""))  # markdown quotes dropped
    assert w.tv_xy_weight.value == "auto" and w.tv_xy_weight.number.enabled is False
    assert w.calibrate_gain.value is True and w.calibrate_pixel_size.value is False
    assert w.calibration_from_stage.value == SolverConfig().calibration_from_stage + 1  # numbered from 1, as the status
    assert schema_widget(Optics, "n_background", clamp=True).min == 1
    with pytest.raises(TypeError):
        schema_widget(SolverConfig, "stages")
    # no experimental setting in the widget (issue 24: settings in tiers); a loaded file keeps its value for the run
    from napari_fdt.napari.widgets.widget_settings import SETTING_FIELDS
    from napari_fdt.schema import tier

    assert not [n for n in SETTING_FIELDS if tier(fields[n]) == "experimental"] and not hasattr(w, "parts_rerun")
    w.set_config(dataclasses.replace(SolverConfig(), parts_rerun="finest"))
    assert w.config().parts_rerun == "finest"


def test_error_curve_updates_during_a_run(make_napari_viewer, qtbot, tmp_path) -> None:
    """With a validation share, the widget's curve gets training and validation points while the worker runs."""
    sim = tiny_scene(grid=4, seed=3)
    folder = write_acquisition(sim.acquisition, tmp_path / "sixteen")
    viewer = make_napari_viewer()
    _open(viewer, folder)
    w = _docked(viewer, ReconstructionWidget(viewer))
    _settings(w, "2x10, 1x40", final_stage_min_passes=24)  # the default
    w.validation_fraction.value = 0.2
    statuses, on_update = [], w._on_update

    def recorded(update) -> None:
        on_update(update)
        statuses.append(w.status.value)

    w._on_update = recorded  # (the worker takes the widget's handler at the click)
    w.run_button.clicked.emit()
    # 16 images in batches of 4: the finest stage's 40 iterations are 10 passes, lengthened to 24 passes = 96 iterations,
    # which the progress bar, the curve's range and the status know as the run starts (no update has arrived yet)
    assert w.progress.max == 10 + 96 and w.curve.curve.total_iterations == 10 + 96 and "96 iterations" in w.status.value
    qtbot.waitUntil(lambda: len(w.curve.curve.validation) >= 3, timeout=60_000)
    assert w.running or len(w.curve.curve.validation) < 106  # points arrive before the run ends, one per snapshot
    _wait_done(qtbot, w)
    assert w.feedback.last_error is None
    curve = w.curve.curve
    # snapshot_every 1: 10 + 96 iterations, but for the first stage's first ones, which the winning TV trial ran (its
    # snapshot is a trial's: no curve point)
    from napari_fdt.recon.loop.phases import probe_iterations

    assert len(curve.validation) == len(curve.train) == 106 - probe_iterations(10)
    assert w._report["stage_lengths"]["iterations"] == [10, 96] and w._report["config"]["stages"][1]["iterations"] == 40
    assert all(0 < v < 1 for _, v in curve.validation)
    assert w._report["validation"]["n_images"] == 3 and "validation" in w.curve_caption.value
    # the time left says up to what the choices still open could add (the TV weight, the model parts), then no more
    running = [t for t in statuses if "elapsed" in t]  # the snapshots' lines
    with_top = [i for i, t in enumerate(running) if "(up to " in t and "as the data choose)" in t]
    assert with_top and with_top == list(range(len(with_top))) and len(with_top) < len(running), running[-3:]


def test_the_widget_estimates_the_resolution_when_asked(make_napari_viewer, qtbot, tmp_path) -> None:
    """"estimate resolution" checked: after the run the halves run in the worker, the status says so, and the result
    lines and the report hold the half-set resolution (issue 25)."""
    sim = tiny_scene(grid=4, seed=2)
    folder = write_acquisition(sim.acquisition, tmp_path / "sixteen")
    viewer = make_napari_viewer()
    _open(viewer, folder)
    w = _docked(viewer, ReconstructionWidget(viewer))
    _settings(w, "2x6, 1x8")
    w.half_set_resolution.value = True
    assert w.config().half_set_resolution is True
    seen: list[str] = []
    on_update = w._on_update

    def status_after(update):
        on_update(update)
        seen.append(w.status.value)

    w._on_update = status_after
    w.run_button.clicked.emit()
    _wait_done(qtbot, w)
    assert w.feedback.last_error is None
    res = w._report.get("resolution")
    assert any(s.startswith("estimating the resolution") for s in seen), seen[-5:]
    assert res["n_images"] == [8, 8] and res["lateral_um"] > 0 and res["axial_um"] > 0
    assert "resolution (half-set FSC): lateral" in w.results.value


def test_the_widget_adds_the_error_bound_and_the_doubtful_structure(make_napari_viewer, qtbot, tmp_path) -> None:
    """"error bound" checked: after the run the replicates run in the worker process, and the viewer gets the bound (RI
    units, the volume's grid) and a labels layer marking exactly the structure within its bound (issue 50)."""
    from napari_fdt.napari.result_view import STRUCTURE_DN

    sim = tiny_scene(grid=3, seed=1)
    folder = write_acquisition(sim.acquisition, tmp_path / "nine")
    viewer = make_napari_viewer()
    _open(viewer, folder)
    w = _docked(viewer, ReconstructionWidget(viewer))
    _settings(w, "2x6, 1x8")
    w.error_bounds.value = True
    assert w.config().error_bounds is True
    w.run_button.clicked.emit()
    _wait_done(qtbot, w)
    assert w.feedback.last_error is None
    section = w._report["error_bounds"]
    bound_layer = next(la for la in viewer.layers if la.name.endswith("error bound"))
    doubt = next(la for la in viewer.layers if la.name.endswith("structure within its bound"))
    ri = np.asarray(w._ri_layer.data)
    bound = np.asarray(bound_layer.data)
    assert bound.shape == ri.shape and np.allclose(bound_layer.scale, w._ri_layer.scale)
    assert float(bound.mean()) == pytest.approx(section["mean_bound"], rel=1e-5)
    dn = np.abs(ri - sim.acquisition.optics.n_background)
    np.testing.assert_array_equal(np.asarray(doubt.data) == 1, (dn > STRUCTURE_DN) & (dn <= bound))
    assert "error bound: mean" in w.results.value


# -- issue 14/15: nothing a user made is lost, the hand-off to the command line, the screen ---------------------------


def test_a_second_run_keeps_the_first_and_calibration_keeps_the_edited_points(make_napari_viewer, qtbot, tiny_dir,
                                                                             tmp_path) -> None:
    viewer = make_napari_viewer()
    layer = _open(viewer, tiny_dir)
    a = _docked(viewer, AcquisitionWidget(viewer))
    w = _docked(viewer, ReconstructionWidget(viewer))
    a.sources_from_file()
    points = viewer.layers[f"{layer.name} sources"]
    edited = points.data.copy()
    edited[0] = (-14.0, 0.5, -0.5)
    points.data = edited
    _settings(w, "2x2, 1x2")  # calibration from the second stage
    w.run_button.clicked.emit()
    _wait_done(qtbot, w)
    first = viewer.layers[f"{layer.name} RI #1 (2x2, 1x2, seed 0)"]
    first_data = np.array(first.data)
    w.seed.value = 5
    w.stages.value = "2x2, 1x3"
    w.run_button.clicked.emit()
    _wait_done(qtbot, w)
    assert w.feedback.last_error is None, w.feedback.label.value
    second = viewer.layers[f"{layer.name} RI #2 (2x2, 1x3, seed 5)"]
    assert first in viewer.layers and np.array_equal(first.data, first_data)  # the first run is untouched
    assert not np.array_equal(second.data, first_data)
    # the calibration went to layers of their own; the hand-edited points are as the user left them
    assert np.array_equal(points.data, edited)
    cal1 = viewer.layers[f"{layer.name} sources calibrated #1"]
    cal2 = viewer.layers[f"{layer.name} sources calibrated #2"]
    assert np.allclose(cal2.data[:, 2], w._rec.sources_um()[:, 0], atol=1e-5) and not np.array_equal(cal1.data, cal2.data)
    assert not np.allclose(cal2.data, edited)  # the calibration moved the sources (in its own layer)
    # Save RI… without an extension gets one that our reader opens
    w.save_result_in_background(tmp_path / "my_cells_RI")
    _wait_tasks(qtbot, w)
    assert (tmp_path / "my_cells_RI.ome.tif").is_file() and (tmp_path / "my_cells_RI.json").is_file()
    assert np.allclose(read_volume_tiff(tmp_path / "my_cells_RI.ome.tif")[0], second.data)


def test_gui_save_acquisition_then_the_command_line_reproduces_the_run(make_napari_viewer, qtbot, tiny_dir, tmp_path) -> None:
    """GUI: edit a source, Save acquisition…, Copy command; the command on the saved folder gives the widget's volume."""
    import shlex

    viewer = make_napari_viewer()
    layer = _open(viewer, tiny_dir)
    a = _docked(viewer, AcquisitionWidget(viewer))
    w = _docked(viewer, ReconstructionWidget(viewer))
    a.sources_from_file()
    points = viewer.layers[f"{layer.name} sources"]
    edited = points.data.copy()
    edited[3] = (-14.5, edited[3, 1] + 0.3, edited[3, 2] - 0.2)
    points.data = edited
    assert w.copy_command() is None and "differ from" in w.feedback.last_error  # not what the folder holds
    saved = tmp_path / "saved"
    a.save_acquisition(saved)
    _wait_tasks(qtbot, a)
    assert a.feedback.last_error is None, a.feedback.label.value
    a.save_acquisition(saved)  # never over an existing folder
    assert a.feedback.last_error.startswith("Save acquisition: ") and "exists" in a.feedback.last_error
    _settings(w, "2x2, 1x2")
    w.seed.value = 7
    command = w.copy_command()
    argv = shlex.split(command)
    assert argv[:3] == ["fdt", "reconstruct", str(saved)] and "--config" in argv and "--out" in argv
    w.run_button.clicked.emit()
    _wait_done(qtbot, w)
    assert w.feedback.last_error is None, w.feedback.label.value
    args = shlex.split(command)[1:]
    # in a terminal, as a user pastes it (not in napari's process, where the solver's Triton import would meet Mesa's GL)
    import subprocess

    proc = subprocess.run([sys.executable, "-c", "import sys; from napari_fdt.cli import main; sys.exit(main(sys.argv[1:]))",
                           *args, "--quiet"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = args[args.index("--out") + 1]
    volume, _ = read_volume_tiff(out)
    assert np.allclose(volume, w._rec.ri_full(), atol=1e-5)
    report = json.loads(open(out.replace(".ome.tif", ".json")).read())
    assert np.allclose(report["calibration"]["initial_sources_um"], w._rec.initial_sources_um)  # the edited start, through the files
    assert np.allclose(w._rec.initial_sources_um[3], (edited[3, 2], edited[3, 1], 14.5))


def test_both_widgets_fit_a_1600x1000_window(make_napari_viewer, qtbot) -> None:
    """Docked together in a 1600×1000 window, Reconstruct, Cancel, the progress bar, the status and result lines and
    Save RI are on screen, without scrolling."""
    from qtpy.QtCore import QPoint, QRect

    viewer = make_napari_viewer(show=True)
    viewer.open_sample(PLUGIN, "beads")
    a = AcquisitionWidget(viewer)
    r = ReconstructionWidget(viewer)
    viewer.window.add_dock_widget(a, name="FDT acquisition", area="right")
    viewer.window.add_dock_widget(r, name="FDT reconstruction", area="right")
    window = r.native.window()
    window.resize(1600, 1000)
    qtbot.wait(200)
    assert window.height() <= 1000 and window.width() <= 1600  # the widgets let the window be this small
    screen = QRect(0, 0, window.width(), window.height())
    r.status.value = "run #1 done: 3 stages in 96.2 s on cpu"  # as long as the lines of a finished run
    r.results.value = ("result: image fit 0.031, validation 0.031 (6 held-out images)\n"
                       "Δn error against the truth 0.118, TV weight 1 (chosen)\n"
                       "resolution (half-set FSC): lateral ≤ 0.66 µm (the grid: the halves agree up to it), axial 6.5 µm "
                       "(the optics' band limit)")
    qtbot.wait(100)
    for name, widget in [("Reconstruct", r.run_button), ("Cancel", r.cancel_button), ("progress", r.progress),
                         ("status", r.status), ("results", r.results),
                         ("Save RI", r.save_button), ("Copy command", r.command_button), ("Apply optics", a.apply_button)]:
        native = widget.native
        rect = QRect(native.mapTo(window, QPoint(0, 0)), native.size())
        assert native.isVisible() and screen.contains(rect), (name, rect, screen)
        if widget is not a.apply_button:  # pinned: never inside a scroll area that could hide them
            assert not native.visibleRegion().isEmpty() and native.visibleRegion().boundingRect().height() == native.height(), name


def test_a_folder_opened_with_the_wrong_reader_points_to_ours(make_napari_viewer, tiny_dir) -> None:
    from napari.utils.notifications import Notification, NotificationSeverity, notification_manager

    viewer = make_napari_viewer()
    a = _docked(viewer, AcquisitionWidget(viewer))
    notification_manager.dispatch(Notification(f"Could not find a backend to open {tiny_dir / 'acquisition.json'}",
                                               severity=NotificationSeverity.ERROR))
    assert "choose napari-fdt in the Choose reader dialog" in a.feedback.label.value


def test_widgets_use_only_public_napari_api(make_napari_viewer, qtbot, tiny_dir, monkeypatch) -> None:
    """Docked through the manifest (napari hands plugins a proxy that flags private access), a fit, a run and a cancel
    touch no private napari attribute, and register no napari task (the close question is the widget's own)."""
    from napari.utils._proxies import PublicOnlyProxy

    private: list[str] = []
    monkeypatch.setattr(PublicOnlyProxy, "_private_attr_warning", staticmethod(lambda name, typ: private.append(f"{typ}.{name}")))
    viewer = make_napari_viewer()
    _open(viewer, tiny_dir)
    _, a = viewer.window.add_plugin_dock_widget(PLUGIN, "FDT acquisition")
    _, w = viewer.window.add_plugin_dock_widget(PLUGIN, "FDT reconstruction")
    a.depth_um.value = "15"
    a.fit_sources()
    _wait_tasks(qtbot, a)
    _settings(w, "2x2, 1x2000")
    w.run_button.clicked.emit()
    qtbot.waitUntil(lambda: "stage 2/2" in w.status.value, timeout=60_000)
    asked = []
    from qtpy.QtWidgets import QMessageBox

    monkeypatch.setattr(QMessageBox, "question", staticmethod(lambda parent, title, text, *a: asked.append(text) or QMessageBox.StandardButton.No))
    assert w._confirm_close() is False and "tiny RI #1 (2x2, 1x2000, seed 0) is running" in asked[0]
    w.cancel_button.clicked.emit()
    _wait_done(qtbot, w)
    assert w.feedback.last_error is None and a.feedback.last_error is None
    assert private == []


def test_3d_shows_the_volume_and_the_sources_not_the_stack(make_napari_viewer, tiny_dir) -> None:
    viewer = make_napari_viewer()
    layer = _open(viewer, tiny_dir)
    a = _docked(viewer, AcquisitionWidget(viewer))
    a.sources_from_file()
    points = viewer.layers[f"{layer.name} sources"]
    assert viewer.dims.axis_labels[:2] == ("image", "z") and viewer.dims.ndim == 4  # separate sliders
    assert np.allclose(points.size, max(3 * 0.33, 0.03 * 32 * 0.33))  # 3 % of the field, at least 3 pixels
    viewer.dims.ndisplay = 3
    assert not layer.visible and points.visible
    viewer.dims.ndisplay = 2
    assert layer.visible and points.visible
