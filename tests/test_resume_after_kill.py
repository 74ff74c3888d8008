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


def _fdt(*args: str) -> list[str]:
    return [sys.executable, "-m", "napari_fdt", "reconstruct", *args, "--quiet", "--device", "cpu"]

def test_a_killed_run_resumed_from_its_folder_equals_the_uninterrupted_run(scene16, tmp_path: Path) -> None:
    acq = write_acquisition(scene16.acquisition, tmp_path / "acq")
    cfg = tmp_path / "cfg.json"  # the TV weights chosen at stage 0's start, a finest stage long enough to be killed in
    cfg.write_text(json.dumps({"stages": [{"factor": 2, "iterations": 20}, {"factor": 1, "iterations": 120}],
                               "batch_size": 4, "validation_fraction": 0.2, "final_stage_min_passes": 0}))
    subprocess.run(_fdt(str(acq), "--out", str(tmp_path / "full.tif"), "--config", str(cfg)), check=True, timeout=600)

    ckpt = tmp_path / "ckpt"
    proc = subprocess.Popen(_fdt(str(acq), "--out", str(tmp_path / "killed.tif"), "--config", str(cfg), "--checkpoint-dir", str(ckpt)))
    try:
        deadline = time.monotonic() + 300
        while not (ckpt / "stage_0.pt").exists():
            assert proc.poll() is None, "the run ended before its first checkpoint"
            assert time.monotonic() < deadline
            time.sleep(0.02)
        time.sleep(0.2)  # inside the finest stage
        assert proc.poll() is None, "the run ended before it could be killed: lengthen its finest stage"
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL and not (tmp_path / "killed.tif").exists()

    subprocess.run(_fdt(str(acq), "--out", str(tmp_path / "resumed.tif"), "--resume", str(ckpt), "--checkpoint-dir", str(ckpt)),
                   check=True, timeout=600)
    full, _ = read_volume_tiff(tmp_path / "full.tif")
    resumed, _ = read_volume_tiff(tmp_path / "resumed.tif")
    assert float(np.max(np.abs(resumed - full))) <= 1e-6
    a, b = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("full", "resumed"))
    assert a["regularisation"]["tv_xy_weight"] == b["regularisation"]["tv_xy_weight"]
    assert a["calibration"]["sources_um"] == b["calibration"]["sources_um"]


def test_the_folder_resumes_from_the_checkpoint_written_last(tmp_path: Path) -> None:
    """By write time, not by stage number (a choice that runs the stages again rewrites stage_0.pt after stage_1.pt);
    an empty folder is refused naming the fix."""
    import pytest

    from napari_fdt.errors import FDTInputError
    from napari_fdt.recon.checkpoint import latest_checkpoint

    with pytest.raises(FDTInputError, match=r"^resume: .* holds no checkpoint"):
        latest_checkpoint(tmp_path)
    (tmp_path / "stage_1.pt").write_bytes(b"1")
    (tmp_path / ".stage_0.pt.tmp").write_bytes(b"being written")
    assert latest_checkpoint(tmp_path).name == "stage_1.pt"
    (tmp_path / "stage_0.pt").write_bytes(b"0")
    os.utime(tmp_path / "stage_1.pt", ns=(1_000_000_000, 1_000_000_000))
    assert latest_checkpoint(tmp_path).name == "stage_0.pt"
