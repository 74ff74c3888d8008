"""The reconstruction widget offers to resume a run it finds checkpoints of (issue 28, item 2), in a real (hidden)
viewer: cancelled in its last stage, the run is offered when its acquisition is selected, and resumed to its end."""

from __future__ import annotations

from napari_fdt.napari.jobs.resume import checkpoint_folder
from napari_fdt.napari.layers import META_PATH
from tests.napari_helpers import META_REPORT, ReconstructionWidget, _docked, _open, _settings, _wait_done


def test_an_interrupted_run_is_offered_and_resumed(make_napari_viewer, qtbot, tiny_dir) -> None:
    viewer = make_napari_viewer()
    acq_layer = _open(viewer, tiny_dir)
    w = _docked(viewer, ReconstructionWidget(viewer))
    assert w.resume_offer is None and w.resume_run.native.isHidden()  # nothing to resume yet
    _settings(w, "2x3, 1x400")
    w.run_button.clicked.emit()
    qtbot.waitUntil(lambda: "stage 2/2" in w.status.value, timeout=60_000)
    w.cancel_button.clicked.emit()
    _wait_done(qtbot, w)
    assert w.cancelled and w._rec.completed_stages == 1
    folder = checkpoint_folder(acq_layer.metadata[META_PATH])
    assert folder.is_dir() and not str(folder).startswith(str(tiny_dir))  # checkpoints beside the user's cache, not the input
    assert w.resume_offer is not None and not w.resume_run.native.isHidden() and not w.resume_run.value
    assert "resume the interrupted run (1 stage done, " in w.resume_run.text  # short: a docked widget is ~400 px wide
    assert "1 stage done; saved" in w.resume_run.tooltip and "with its own settings" in w.resume_run.tooltip
    w.resume_run.value = True
    w.stages.value = "1x2"  # not what runs: the resumed run keeps its own stages
    w.run_button.clicked.emit()
    assert w.resume_run.native.isHidden() and "resuming" in w.status.value
    _wait_done(qtbot, w, timeout_ms=180_000)
    assert not w.cancelled and w._rec.completed_stages == 2
    report = next(layer.metadata[META_REPORT] for layer in viewer.layers if " RI #2 " in layer.name)
    assert report.get("completed_stages") == 2 and [s["iterations"] for s in report["config"]["stages"]] == [3, 400]
    assert not folder.exists() and w.resume_offer is None and w.resume_run.native.isHidden()  # the run ended: nothing left to resume


def test_a_crafted_checkpoint_in_the_resume_folder_is_refused_and_runs_no_code(make_napari_viewer, qtbot, tiny_dir,
                                                                                tmp_path) -> None:
    """Issue 51: a pickle that would run ``touch`` when loaded, put where the widget looks for checkpoints, is offered (the
    offer reads file names only) but refused when resumed: the run fails with the error naming the fix, no code runs."""
    from tests.test_checkpoint_safety import crafted_checkpoint

    viewer = make_napari_viewer()
    folder = checkpoint_folder(str(tiny_dir))
    folder.mkdir(parents=True, exist_ok=True)
    marker = tmp_path / "code_ran"
    crafted_checkpoint(folder / "stage_0.pt", marker)
    acq_layer = _open(viewer, tiny_dir)
    assert checkpoint_folder(acq_layer.metadata[META_PATH]) == folder
    w = _docked(viewer, ReconstructionWidget(viewer))
    assert w.resume_offer is not None and not w.resume_run.native.isHidden()
    _settings(w, "2x3, 1x4")
    w.resume_run.value = True
    w.run_button.clicked.emit()
    _wait_done(qtbot, w)
    assert "failed" in w.status.value
    assert w.feedback.last_error is not None and "no code in it ran" in w.feedback.last_error
    assert not marker.exists()
