"""The smoothing family in napari (issue 47, item 4), in a real (hidden) viewer: members appear as they finish, the
slider shows each, the pick is shown at the end beside the "depends on smoothing" layer, and Save writes the member
shown with a report that says which member it is and why."""

from __future__ import annotations

import json

import numpy as np

from napari_fdt.data.io import write_acquisition
from napari_fdt.recon.run.family import FAMILY_TAUS
from napari_fdt.recon.settings.config import SolverConfig, StageConfig
from tests.napari_helpers import _docked, _open, read_volume_tiff


def test_a_family_runs_shows_its_members_on_a_slider_and_saves_the_one_shown(make_napari_viewer, qtbot, scene16, tmp_path) -> None:
    from napari_fdt.napari.widgets.widget_family import FamilyWidget

    viewer = make_napari_viewer()
    acq_layer = _open(viewer, write_acquisition(scene16.acquisition, tmp_path / "acq"))
    w = _docked(viewer, FamilyWidget(viewer))
    assert w.layer.value is acq_layer and not w.smoothing.enabled
    w.config = SolverConfig(stages=[StageConfig(2, 6), StageConfig(1, 8)], batch_size=4, final_stage_min_passes=0)
    w.device.value = "cpu"
    seen_counts = []
    w.smoothing.changed.connect(lambda _v: seen_counts.append(len(w.members)))
    w.run_button.clicked.emit()
    qtbot.waitUntil(lambda: not w.running and w.family is not None, timeout=240_000)
    assert [m["tau"] for m in w.members] == list(FAMILY_TAUS)
    assert seen_counts[:2] == [2, 3]  # the slider followed the members as they arrived
    pick = w.family["pick"]
    assert w.smoothing.value == pick and "the pick" in w.shown.value and "the pick is" in w.status.value
    entries = w.family["entries"]
    best = min(e["validation_error"] for e in entries)
    assert entries[pick]["validation_error"] <= 1.05 * best and entries[pick]["picked"]
    stack = np.stack([m["ri"] for m in w.members])
    shown = next(layer for layer in viewer.layers if "member shown" in layer.name)
    spread = next(layer for layer in viewer.layers if "depends on smoothing" in layer.name)
    assert np.array_equal(shown.data, stack[pick])
    assert np.allclose(spread.data, stack.max(axis=0) - stack.min(axis=0)) and spread.data.max() > 0
    # move the slider to another member and save it: the file is that member, and its report says so and why
    other = (pick + 1) % len(w.members)
    w.smoothing.value = other
    assert np.array_equal(shown.data, stack[other]) and f"τ_xy {FAMILY_TAUS[other]:g}" in w.shown.value
    out, report_file = w.save_shown(tmp_path / "kept")
    assert out.name == "kept.ome.tif"
    assert np.array_equal(read_volume_tiff(out)[0], stack[other])
    report = json.loads(report_file.read_text())
    member = report["regularisation"]["family_member"]
    assert member["tau"] == FAMILY_TAUS[other] and member["picked"] is False and "chosen by the user" in member["why"]
    assert report["regularisation"]["tv_xy_weight"] == FAMILY_TAUS[other]
    assert [e["tau"] for e in report["regularisation"]["family"]] == list(FAMILY_TAUS)
    assert report["config"]["tv_xy_weight"] == FAMILY_TAUS[other] and report["config"]["tv_family"] == "false"
