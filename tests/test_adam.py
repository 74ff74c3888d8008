"""The run's Adam (recon/calibration/adam.py) is torch's Adam op for op, and a run never imports torch's compiler
(issue 48, item 2: the import was 1.1 s of a 2-core CPU's cold start)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import torch

from napari_fdt.recon.calibration.adam import Adam


def _problem(seed: int):
    g = torch.Generator().manual_seed(seed)
    shapes = [(5, 7), (3,), (4, 2), ()]
    return [torch.randn(s, generator=g, dtype=torch.float32) for s in shapes], g


def _run(cls, steps: int = 7):
    params, g = _problem(0)
    params = [p.clone().requires_grad_() for p in params]
    groups = [{"params": params[:2], "lr": 0.03}, {"params": params[2:], "lr": 0.2, "eps": 1e-6}]
    opt = cls(groups, betas=(0.9, 0.99))
    for k in range(steps):
        opt.zero_grad(set_to_none=True)
        loss = sum(((p - 0.3 * k) ** 2 * (1 + i)).sum() for i, p in enumerate(params) if not (k % 3 == 1 and i == 3))
        loss.backward()  # (the last parameter has no gradient every third step: skipped, as torch skips it)
        opt.step()
        if k == 3:
            opt.param_groups[0]["lr"] = 0.01  # the finest stage's decaying step changes a group's rate
    return [p.detach() for p in params], opt.state_dict()


def test_the_step_is_torchs_bit_for_bit() -> None:
    ours, our_state = _run(Adam)
    theirs, their_state = _run(torch.optim.Adam)
    assert all(torch.equal(a, b) for a, b in zip(ours, theirs))
    for i, st in their_state["state"].items():
        assert set(st) == set(our_state["state"][i]) and all(torch.equal(st[k], our_state["state"][i][k]) for k in st)
    assert our_state["param_groups"] == their_state["param_groups"]


def test_a_state_dict_loads_across_the_two() -> None:
    """A checkpoint's optimiser state written by torch's Adam (every checkpoint before this class) loads into ours."""
    params, _ = _problem(1)
    a = [p.clone().requires_grad_() for p in params]
    theirs = torch.optim.Adam(a, lr=0.1)
    sum((p * p).sum() for p in a).backward()
    theirs.step()
    ours = Adam([p.detach().clone().requires_grad_() for p in params], lr=0.1)
    ours.load_state_dict(theirs.state_dict())
    assert torch.equal(ours.state_dict()["state"][0]["exp_avg"], theirs.state_dict()["state"][0]["exp_avg"])


def test_a_run_does_not_import_the_compiler_nor_sympy() -> None:
    code = (
        "import sys\n"
        "from benchmarks.scenes import tiny_scene\n"
        "from napari_fdt.recon.run.solver import Reconstructor\n"
        "from napari_fdt.recon.settings.config import SolverConfig, StageConfig\n"
        "rec = Reconstructor(tiny_scene(grid=4, seed=2).acquisition, SolverConfig(stages=[StageConfig(2, 3), StageConfig(1, 3)],"
        " batch_size=4, final_stage_min_passes=0), device='cpu')\n"
        "list(rec.run())\n"
        "rec.state_dict(); rec.calibration.optimiser.rows\n"
        "assert rec.completed_stages == 2\n"
        "print('torch._dynamo' in sys.modules, 'sympy' in sys.modules)\n"
    )
    root = Path(__file__).resolve().parents[1]  # (benchmarks importable)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=root)
    assert out.returncode == 0, out.stderr[-2000:]
    # neither torch's compiler nor sympy (torch.broadcast_shapes imports it on its first call: 0.3 s of a cold run)
    assert out.stdout.strip().splitlines()[-1] == "False False"
