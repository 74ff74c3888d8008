"""The plugin's computation process without Qt: a run relayed from the child equals the job run here, errors cross
with their message, a child that dies is reported with its signal, and the result-view helpers' numbers."""

from __future__ import annotations

import pickle
import signal
import threading

import numpy as np
import pytest

from benchmarks.scenes import tiny_scene
from napari_fdt.errors import FDTInputError
from napari_fdt.napari.jobs.compute_process import ComputeError, portable_exception
from napari_fdt.napari.jobs.job import reconstruction_job
from napari_fdt.napari.jobs.remote_job import ComputeProcessDied, RunResult, describe_exit, remote_reconstruction
from napari_fdt.napari.result_view import content_slice, results_line, ri_contrast_limits
from napari_fdt.recon.settings.config import SolverConfig, StageConfig


@pytest.fixture(scope="module")
def tiny():
    return tiny_scene(grid=3, seed=1)


def _drain(gen):
    updates = []
    while True:
        try:
            updates.append(next(gen))
        except StopIteration as end:
            return updates, end.value


def test_a_run_in_the_child_equals_the_job_here(tiny) -> None:
    acq = tiny.acquisition
    config = SolverConfig(stages=[StageConfig(2, 3), StageConfig(1, 3)], batch_size=4, snapshot_every=1,
                          tv_xy_weight=0.0, tv_z_weight=0.0, final_stage_min_passes=0)
    local_updates, local = _drain(reconstruction_job(acq, config, device="cpu", stop=threading.Event()))
    done = threading.Event()
    updates, remote = _drain(remote_reconstruction(acq, config, device="cpu", stop=threading.Event(), done=done))
    try:
        assert done.is_set() and isinstance(remote.rec, RunResult)
        # same stream (the child's snapshots without their stage-grid volume: the RI comes beside them)
        kinds = [(u.kind, u.snapshot.stage, u.snapshot.iteration) for u in updates if u.snapshot is not None]
        assert kinds == [(u.kind, u.snapshot.stage, u.snapshot.iteration) for u in local_updates if u.snapshot is not None]
        assert all(u.snapshot.delta_n.size == 0 for u in updates if u.snapshot is not None)
        # same volume, sources and report to float32 rounding (same seed, same batch order, same thread count)
        assert remote.completed_stages == 2 and not remote.cancelled
        assert np.allclose(remote.ri, local.ri, atol=1e-5) and np.allclose(remote.sources_um, local.sources_um, atol=1e-5)
        assert remote.report["completed_stages"] == local.report["completed_stages"] == 2
        # the child keeps the solver: predicted vs measured, as the solver here predicts it
        pred, meas = remote.rec.predicted_vs_measured(2)
        assert np.allclose(meas, acq.images_float32()[2]) and np.allclose(pred, local.rec.predict([2])[0], rtol=1e-4, atol=1e-6)
    finally:
        remote.rec.close()
    with pytest.raises(FDTInputError, match="the computation process of this run has ended"):
        remote.rec.predicted_vs_measured(2)


def test_an_error_in_the_child_arrives_as_itself(tiny) -> None:
    acq = tiny.acquisition
    blank = type(acq)(images=np.zeros_like(acq.images), optics=acq.optics, sources_um=acq.sources_um)
    with pytest.raises(FDTInputError, match="images: are all zero") as err:
        _drain(remote_reconstruction(blank, SolverConfig(stages=[StageConfig(1, 2)]), device="cpu", stop=threading.Event()))
    assert err.value.field == "images" and err.value.fix


def test_a_child_that_dies_is_reported_with_its_signal(tiny) -> None:
    config = SolverConfig(stages=[StageConfig(2, 2), StageConfig(1, 2)], batch_size=4, tv_xy_weight=0.0, tv_z_weight=0.0,
                          final_stage_min_passes=0)
    gen = remote_reconstruction(tiny.acquisition, config, device="cpu", stop=threading.Event(),
                                target="crashing_job:crash_after_first_stage")
    with pytest.raises(ComputeProcessDied) as err:
        _drain(gen)
    assert err.value.exit_code == -signal.SIGKILL and err.value.completed_stages == 1
    assert err.value.ri is not None and err.value.ri.shape == (4, 32, 32)
    assert "killed by signal 9 (SIGKILL): often the system ran out of memory" in str(err.value)


def test_exceptions_cross_the_process_boundary() -> None:
    e = pickle.loads(pickle.dumps(FDTInputError("na", "1.5 is not below 1.33", "lower it")))
    assert (e.field, e.problem, e.fix, str(e)) == ("na", "1.5 is not below 1.33", "lower it", "na: 1.5 is not below 1.33 (lower it)")
    # superqt drops the error signal of a RuntimeError (it takes it for a deleted Qt object): never one of those
    assert isinstance(portable_exception(RuntimeError("CUDA error: out of memory")), ComputeError)

    class Unpicklable(Exception):
        def __init__(self, a, b):
            super().__init__(a)

    assert str(portable_exception(Unpicklable("x", "y"))) == "Unpicklable: x"
    assert describe_exit(-11) == "killed by signal 11 (SIGSEGV): a crash in native code" and describe_exit(1) == "exit status 1"


def test_view_helpers() -> None:
    ri = np.full((4, 8, 8), 1.33, np.float32)
    ri[2, 2:6, 2:6] = 1.38
    ri[1, 3, 3] = 1.32
    assert content_slice(ri, 1.33) == 2
    lo, hi = ri_contrast_limits(ri, 1.33)
    assert lo <= 1.33 and 1.33 < hi <= 1.38 + 1e-6
    assert ri_contrast_limits(np.full((2, 4, 4), 1.33, np.float32), 1.33)[1] - 1.33 == pytest.approx(1e-4)  # never zero wide
    line = results_line({"image_fit": {"image_relative_error": 0.0305}, "validation": {"error": 0.0311, "n_images": 6},
                         "regularisation": {"tv_xy_weight": 1.0, "chosen": {"stage": 1}}}, 0.1184)
    assert line == ("result: image fit 0.030, validation 0.031 (6 held-out images)\n"
                    "Δn error against the truth 0.118, TV weight 1 (chosen)")
    assert results_line({"regularisation": {"tv_xy_weight": 3.0, "chosen": None}}) == "result: no image fit"
