"""A run killed with SIGKILL (no chance to clean up) and resumed from its checkpoint folder ends as the uninterrupted
run (issue 28, item 2): the same choices, batch order and optimiser states, max |ΔRI| ≤ 1e-6 on the CPU with the same
thread count. Small size, in separate processes, as a user's ``fdt reconstruct`` would run."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from napari_fdt import read_volume_tiff, write_acquisition
from napari_fdt.recon.loop.checkpoint import latest_checkpoint


def _fdt(*args: str) -> list[str]:
    return [sys.executable, "-m", "napari_fdt", "reconstruct", *args, "--quiet", "--device", "cpu"]

def test_a_killed_run_resumed_from_its_folder_equals_the_uninterrupted_run(scene16, tmp_path: Path) -> None:
    acq = write_acquisition(scene16.acquisition, tmp_path / "acq")
    cfg = tmp_path / "cfg.json"  # the TV weights chosen at stage 0's start, a finest stage long enough to be killed in
    cfg.write_text(json.dumps({"stages": [{"factor": 2, "iterations": 20}, {"factor": 1, "iterations": 120}],
                               "batch_size": 4, "validation_fraction": 0.2, "final_stage_min_passes": 0,
                               "checkpoint_every_s": 0}))  # a checkpoint at every snapshot, inside the stages too
    subprocess.run(_fdt(str(acq), "--out", str(tmp_path / "full.tif"), "--config", str(cfg)), check=True, timeout=600)

    ckpt = tmp_path / "ckpt"
    proc = subprocess.Popen(_fdt(str(acq), "--out", str(tmp_path / "killed.tif"), "--config", str(cfg), "--checkpoint-dir", str(ckpt)))
    try:
        deadline = time.monotonic() + 300
        while not list(ckpt.glob("stage_1_it*.pt")):  # a checkpoint inside the finest stage
            assert proc.poll() is None, "the run ended before a checkpoint inside its finest stage"
            assert time.monotonic() < deadline
            time.sleep(0.02)
        assert proc.poll() is None, "the run ended before it could be killed: lengthen its finest stage"
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL and not (tmp_path / "killed.tif").exists()
    assert latest_checkpoint(ckpt).name.startswith("stage_1_it")  # the resume goes on inside the finest stage

    subprocess.run(_fdt(str(acq), "--out", str(tmp_path / "resumed.tif"), "--resume", str(ckpt), "--checkpoint-dir", str(ckpt)),
                   check=True, timeout=600)
    full, _ = read_volume_tiff(tmp_path / "full.tif")
    resumed, _ = read_volume_tiff(tmp_path / "resumed.tif")
    assert float(np.max(np.abs(resumed - full))) <= 1e-6
    a, b = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("full", "resumed"))
    assert a["regularisation"]["tv_xy_weight"] == b["regularisation"]["tv_xy_weight"]
    assert a["calibration"]["sources_um"] == b["calibration"]["sources_um"]
    assert not list(ckpt.glob("stage_*_it*.pt")) and (ckpt / "stage_1.pt").exists()  # pruned by the stage's end


def test_a_run_stopped_inside_a_stage_resumes_there_and_equals_the_unbroken_run(scene16, tmp_path: Path) -> None:
    """In one process: a run stopped inside its finest stage leaves a checkpoint of that stage's progress (its RI
    optimiser, best iterate, record, the state the model-parts choice starts it again from); resumed from the folder it
    ends bit-identical to the unbroken run, the choice of model parts at the stage's end included."""
    from napari_fdt.recon.run.solver import Reconstructor
    from napari_fdt.recon.settings.config import SolverConfig, StageConfig

    cfg = SolverConfig(stages=[StageConfig(2, 6), StageConfig(1, 12)], batch_size=4, snapshot_every=2, validation_fraction=0.2,
                       final_stage_min_passes=0, checkpoint_every_s=0.0)
    unbroken = Reconstructor(scene16.acquisition, cfg, device="cpu")
    list(unbroken.run())
    rec = Reconstructor(scene16.acquisition, cfg, device="cpu")
    seen = []
    for snap in rec.run(checkpoint_dir=tmp_path):
        seen.append((snap.stage, snap.iteration))
        if (snap.stage, snap.iteration) == (1, 6):
            break
    assert latest_checkpoint(tmp_path).name == "stage_1_it6.pt" and [p.name for p in tmp_path.glob("stage_*_it*.pt")] == ["stage_1_it6.pt"]
    resumed = Reconstructor.from_checkpoint(tmp_path, scene16.acquisition, device="cpu")
    assert resumed.completed_stages == 1
    snaps = list(resumed.run(checkpoint_dir=tmp_path))
    assert [(s.stage, s.iteration) for s in snaps] == [(1, 8), (1, 10), (1, 12)]
    assert np.array_equal(resumed.delta_n_full(), unbroken.delta_n_full())
    assert np.array_equal(resumed.sources_um(), unbroken.sources_um())
    assert [r.validation_error for r in resumed.stages] == [r.validation_error for r in unbroken.stages]
    assert resumed.parts_choice.to_dict()["parts"] == unbroken.parts_choice.to_dict()["parts"]


def test_the_folder_resumes_from_the_checkpoint_written_last(tmp_path: Path) -> None:
    """By write time, not by stage number (a choice that runs the stages again rewrites stage_0.pt after stage_1.pt);
    an empty folder is refused naming the fix."""
    import pytest

    from napari_fdt.errors import FDTInputError

    with pytest.raises(FDTInputError, match=r"^resume: .* holds no checkpoint"):
        latest_checkpoint(tmp_path)
    (tmp_path / "stage_1.pt").write_bytes(b"1")
    (tmp_path / ".stage_0.pt.tmp").write_bytes(b"being written")
    assert latest_checkpoint(tmp_path).name == "stage_1.pt"
    (tmp_path / "stage_0.pt").write_bytes(b"0")
    os.utime(tmp_path / "stage_1.pt", ns=(1_000_000_000, 1_000_000_000))
    assert latest_checkpoint(tmp_path).name == "stage_0.pt"


def test_the_checkpoint_interval_counts_computation_not_the_consumers_pauses(scene16, tmp_path: Path) -> None:
    """A consumer that holds every snapshot for 0.4 s (a viewer drawing, a slow disk) does not make the run write more
    checkpoints: ``checkpoint_every_s`` counts the solver's own seconds (its ``elapsed_s``)."""
    from napari_fdt.recon.run.solver import Reconstructor
    from napari_fdt.recon.settings.config import SolverConfig, StageConfig

    cfg = SolverConfig(stages=[StageConfig(1, 10)], batch_size=4, snapshot_every=1, validation_fraction=0.0,
                       final_stage_min_passes=0, checkpoint_every_s=2.0, tv_xy_weight=0.0, tv_z_weight=0.0)
    rec = Reconstructor(scene16.acquisition, cfg, device="cpu")
    written = []
    for snap in rec.run(checkpoint_dir=tmp_path):
        written += [p.name for p in tmp_path.glob("stage_0_it*.pt") if p.name not in written]
        if not snap.stage_complete:
            time.sleep(0.4)  # 9 pauses: 3.6 s of the consumer's, past the 2 s interval twice
    compute_s = rec.stages[0].seconds
    assert compute_s < 2.0, f"the stage's own computation took {compute_s:.1f} s: the test needs it below the interval"
    assert written == [], written


def test_ctrl_c_writes_the_last_complete_stage(scene16, tmp_path: Path) -> None:
    """Ctrl-C (SIGINT) inside the finest stage: `fdt reconstruct` writes the last complete stage, says so in the report
    and exits with 130 (recon.session.finish_run, shared with the plugin); its volume equals stage 1's checkpoint."""
    import torch

    from napari_fdt.recon.problem.volume import RIVolume

    acq = write_acquisition(scene16.acquisition, tmp_path / "acq")
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"stages": [{"factor": 2, "iterations": 10}, {"factor": 1, "iterations": 4000}],
                               "batch_size": 4, "validation_fraction": 0.2, "final_stage_min_passes": 0,
                               "tv_xy_weight": 1.0, "tv_z_weight": 0.5}))
    ckpt = tmp_path / "ckpt"
    out = tmp_path / "cut.tif"
    # SIGINT as a terminal delivers it: a suite started in the background (``pytest &``) hands its children SIGINT
    # ignored, and Python then installs no KeyboardInterrupt for it
    proc = subprocess.Popen(_fdt(str(acq), "--out", str(out), "--config", str(cfg), "--checkpoint-dir", str(ckpt)),
                            stderr=subprocess.PIPE, text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 300
        while not (ckpt / "stage_0.pt").exists():
            assert proc.poll() is None and time.monotonic() < deadline
            time.sleep(0.02)
        time.sleep(1.0)  # inside the finest stage
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "interrupted: writing the last complete stage (1/2)" in err
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["cancelled"] is True and report["completed_stages"] == 1
    written, _ = read_volume_tiff(out)
    state = torch.load(ckpt / "stage_0.pt", map_location="cpu", weights_only=False)
    stage0 = RIVolume.from_state_dict(state["volume"], torch.device("cpu"), torch.float32)
    expected = stage0.full_resolution(state["volume_factor"], written.shape[1:]).numpy() + scene16.acquisition.optics.n_background
    assert float(np.max(np.abs(written - expected))) <= 1e-6
