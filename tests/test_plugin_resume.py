"""The plugin's runs leave checkpoints, and an interrupted run is offered and resumed (issue 28, item 2): the job without
Qt here, the widget in tests/test_napari_resume_widget.py."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest

from napari_fdt.napari.jobs import resume
from napari_fdt.napari.jobs.job import reconstruction_job
from napari_fdt.recon.settings.config import SolverConfig, StageConfig


def _drain(gen, on_update=None):
    while True:
        try:
            update = next(gen)
        except StopIteration as end:
            return end.value
        if on_update is not None:
            on_update(update)


CONFIG = SolverConfig(stages=[StageConfig(2, 4), StageConfig(1, 8)], batch_size=4, snapshot_every=1,
                      tv_xy_weight=1.0, tv_z_weight=0.5, final_stage_min_passes=0)


def test_checkpoint_folder_is_per_acquisition_and_outside_it(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("NAPARI_FDT_CHECKPOINTS", str(tmp_path / "cache"))
    a, b = resume.checkpoint_folder(tmp_path / "acq_a"), resume.checkpoint_folder(tmp_path / "acq_b")
    assert a != b and a.parent == b.parent == tmp_path / "cache" and a.name.startswith("acq_a-")
    assert resume.checkpoint_folder(str(tmp_path / "acq_a")) == a  # the same folder, however it is spelled
    assert resume.checkpoint_folder(None) is None  # an acquisition made in memory: nothing to find it by
    assert resume.interrupted_run(a) is None  # no folder yet
    a.mkdir(parents=True)
    (a / "stage_0.pt").write_bytes(b"x")
    time.sleep(0.01)
    (a / "stage_1_it40.pt").write_bytes(b"x")
    offer = resume.interrupted_run(a)
    assert offer.latest.name == "stage_1_it40.pt" and offer.stages_done == 1 and offer.in_stage_iteration == 40
    assert offer.describe().startswith("1 stage done, in stage 2 at iteration 40; saved ")
    assert offer.short().startswith("stage 2, it. 40, ")
    os.utime(a / "stage_0.pt", ns=(time.time_ns() + 10**9, time.time_ns() + 10**9))  # a later write wins, as resuming picks
    assert resume.interrupted_run(a).stages_done == 1 and resume.interrupted_run(a).in_stage_iteration is None
    resume.clear(a)
    assert not a.exists() and resume.interrupted_run(a) is None


def test_cancelled_job_is_resumed_to_the_uninterrupted_result(tiny_sim, tmp_path) -> None:
    acq = tiny_sim.acquisition
    whole = _drain(reconstruction_job(acq, CONFIG, device="cpu", stop=threading.Event()))
    folder = tmp_path / "checkpoints"
    stop = threading.Event()

    def cancel_after_first_stage(update) -> None:
        if update.snapshot is not None and update.snapshot.stage_complete and update.snapshot.stage == 0:
            stop.set()

    first = _drain(reconstruction_job(acq, CONFIG, device="cpu", stop=stop, checkpoint_dir=str(folder)), cancel_after_first_stage)
    assert first.cancelled and first.completed_stages == 1
    offer = resume.interrupted_run(folder)
    assert offer is not None and offer.stages_done == 1 and offer.latest.name == "stage_0.pt"
    other = SolverConfig(stages=[StageConfig(1, 2)])  # a resumed run keeps its own settings, not the widget's new ones
    resumed = _drain(reconstruction_job(acq, other, device="cpu", stop=threading.Event(), checkpoint_dir=str(folder), resume=True))
    assert not resumed.cancelled and resumed.completed_stages == 2
    assert np.abs(resumed.ri - whole.ri).max() <= 1e-6
    assert np.abs(resumed.sources_um - whole.sources_um).max() <= 1e-6
    assert not folder.exists()  # a run that ends leaves nothing to resume


def test_a_fresh_run_deletes_the_old_checkpoints(tiny_sim, tmp_path) -> None:
    folder = tmp_path / "checkpoints"
    folder.mkdir()
    (folder / "stage_5.pt").write_bytes(b"not a checkpoint")  # what an old run left
    stop = threading.Event()
    seen = []

    def look_then_cancel(update) -> None:
        if update.snapshot is not None and update.snapshot.stage_complete and update.snapshot.stage == 0:
            seen.append(sorted(p.name for p in folder.glob("*.pt")))
            stop.set()

    result = _drain(reconstruction_job(tiny_sim.acquisition, CONFIG, device="cpu", stop=stop, checkpoint_dir=str(folder)),
                    look_then_cancel)
    assert result.cancelled and seen == [["stage_0.pt"]]


@pytest.mark.parametrize("broken", [b"", b"garbage"])
def test_resuming_from_an_unreadable_checkpoint_names_the_fix(tiny_sim, tmp_path, broken) -> None:
    from napari_fdt.errors import FDTInputError

    folder = tmp_path / "checkpoints"
    folder.mkdir()
    (folder / "stage_0.pt").write_bytes(broken)
    with pytest.raises(FDTInputError) as err:
        _drain(reconstruction_job(tiny_sim.acquisition, CONFIG, device="cpu", stop=threading.Event(),
                                  checkpoint_dir=str(folder), resume=True))
    assert err.value.field == "resume"
