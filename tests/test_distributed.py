"""Data-parallel reconstruction (torch.distributed): sharding, loss normalisation, and two gloo ranks on CPU
giving the single-process result.

Tolerances of the two-rank comparison. The ranks sum partial gradients (their images) where one process sums
over the whole batch, so the float32 results differ by reduction order only. What that amounts to after the
run was measured on this scene by perturbing a single-process run's predictions by about one float32 ulp
(relative noise 2^-24 per pixel, three seeds) and comparing with the unperturbed run: max |ΔΔn| 1.2e-7 to
3.6e-7 (Δn up to 0.0225), sources 1.9e-6 to 5.7e-6 µm, gains 0.7e-7 to 3.7e-7 relative; two gloo ranks
against one process gave 3.6e-7, 5.7e-6 µm and 1.2e-7. The tolerances below are about ten times those.
Errors of the scheme are far above them: each rank normalising by its own images gave 0.014 in Δn,
the regularisers counted on both ranks 0.0018, a checkpoint without the other rank's Adam moments 0.0054.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import napari_fdt
from benchmarks.scenes import tiny_scene
from napari_fdt.cli import main
from napari_fdt.data.io import read_volume_tiff, write_acquisition
from napari_fdt.errors import FDTInputError
from napari_fdt.recon.problem import distributed
from napari_fdt.recon.problem.losses import BatchShare, LossWeights, total_loss
from napari_fdt.recon.settings.config import SolverConfig, StageConfig

TESTS = Path(__file__).resolve().parent
DN_TOL = 1e-5  # absolute, on Δn (4e-6 held with the full-window model; the split-field model's table products round
# differently with the number of rows a rank's batch gives them (BLAS blocking): 5.5e-6 measured, 1e-4 of the largest Δn)
SOURCES_TOL_UM = 6e-5
GAIN_RTOL = 4e-6
N_BG = 1.33

# --------------------------------------------------------------------------------------------
# Sharding and set-up (no process group)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("world", [1, 2, 3, 4])
def test_each_image_of_a_batch_goes_to_exactly_one_rank_in_order(world: int) -> None:
    batch = torch.tensor([8, 0, 2, 7, 5, 3, 6])
    parts = [distributed.owned(batch, r, world) for r in range(world)]
    assert sorted(torch.cat(parts).tolist()) == sorted(batch.tolist())
    for r, part in enumerate(parts):
        assert all(i % world == r for i in part.tolist())
        positions = [batch.tolist().index(i) for i in part.tolist()]
        assert positions == sorted(positions)  # the batch's order is kept


def test_world_from_env_reads_torchrun_variables() -> None:
    assert distributed.world_from_env({}) == (1, 0, 0, 1)
    assert distributed.world_from_env({"WORLD_SIZE": "1", "RANK": "0"}) == (1, 0, 0, 1)
    env = {"WORLD_SIZE": "4", "RANK": "3", "LOCAL_RANK": "1", "LOCAL_WORLD_SIZE": "2"}
    assert distributed.world_from_env(env) == (4, 3, 1, 2)
    with pytest.raises(FDTInputError) as exc:
        distributed.world_from_env({"WORLD_SIZE": "2"})
    assert exc.value.field == "RANK"
    with pytest.raises(FDTInputError) as exc:
        distributed.world_from_env({"WORLD_SIZE": "2", "RANK": "2"})
    assert exc.value.field == "RANK"


def test_not_launched_distributed_nothing_happens(monkeypatch) -> None:
    for name in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(name, raising=False)
    assert distributed.setup("cpu") is None
    monkeypatch.setenv("WORLD_SIZE", "1")
    assert distributed.setup("cpu") is None
    assert not torch.distributed.is_initialized()
    distributed.teardown(None)


def test_backend_choice(monkeypatch) -> None:
    monkeypatch.delenv("FDT_DIST_BACKEND", raising=False)
    monkeypatch.setattr(torch.distributed, "is_nccl_available", lambda: True)
    cpu, gpu = torch.device("cpu"), torch.device("cuda", 0)
    assert distributed.choose_backend(cpu) == "gloo"
    assert distributed.choose_backend(gpu) == "nccl"
    assert distributed.choose_backend(gpu, ranks_per_gpu=2) == "gloo"  # NCCL refuses two ranks on one GPU
    assert distributed.choose_backend(gpu, "gloo") == "gloo"
    monkeypatch.setenv("FDT_DIST_BACKEND", "gloo")
    assert distributed.choose_backend(gpu) == "gloo"
    assert distributed.choose_backend(gpu, "nccl") == "nccl"  # the command-line option wins over the variable
    monkeypatch.setenv("FDT_DIST_BACKEND", "mpi")
    with pytest.raises(FDTInputError) as exc:
        distributed.choose_backend(cpu)
    assert exc.value.field == "FDT_DIST_BACKEND"
    with pytest.raises(FDTInputError, match="NCCL needs CUDA"):
        distributed.choose_backend(cpu, "nccl")


def test_rank_device_maps_local_rank_to_a_gpu(monkeypatch) -> None:
    import napari_fdt.device as device_module

    assert distributed.rank_device("cpu", 3) == torch.device("cpu")
    monkeypatch.setattr(device_module, "resolve_device", lambda d: torch.device("cuda" if d == "auto" else d))
    assert distributed.rank_device("auto", 3, gpu_count=4) == torch.device("cuda", 3)
    assert distributed.rank_device("cuda", 3, gpu_count=2) == torch.device("cuda", 1)  # two ranks share GPU 1
    assert distributed.rank_device("cuda:0", 3, gpu_count=4) == torch.device("cuda", 0)  # explicit: kept


# --------------------------------------------------------------------------------------------
# Normalisation: the parts of a batch add up to the batch
# --------------------------------------------------------------------------------------------


def _loss_inputs(masked: bool):
    g = torch.Generator().manual_seed(3)
    b, h, w = 5, 16, 16
    pred = torch.rand(b, h, w, generator=g, dtype=torch.float64).requires_grad_()
    target = torch.rand(b, h, w, generator=g, dtype=torch.float64)
    volume = torch.rand(3, 8, 8, generator=g, dtype=torch.float64).requires_grad_()
    mask = (torch.rand(b, h, w, generator=g) > 0.3).to(torch.float64) if masked else None
    weights = LossWeights(l1_l2_total=1.0, ssim=0.3, tv_xy=0.01, tv_z=0.02, schedule_start=0.2, schedule_end=0.8)
    return pred, target, volume, mask, weights


@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("world", [2, 3, 6])  # 6 ranks for 5 images: one rank has none
def test_the_ranks_losses_and_gradients_add_up_to_the_whole_batch(masked: bool, world: int) -> None:
    pred, target, volume, mask, weights = _loss_inputs(masked)
    full, full_terms = total_loss(pred, target, volume, weights, 0.5, mask=mask, data_range=1.0)
    g_pred, g_vol = torch.autograd.grad(full, (pred, volume))

    batch = torch.arange(pred.shape[0])
    share_total = torch.zeros((), dtype=torch.float64)
    sums = {k: 0.0 for k in ("l1", "l2", "ssim_loss", "total")}
    p_grad, v_grad = torch.zeros_like(pred), torch.zeros_like(volume)
    for rank in range(world):
        local = distributed.owned(batch, rank, world)
        share = BatchShare.of_batch(mask, tuple(pred.shape), regularisers=rank == 0)
        loss, terms = total_loss(pred[local], target[local], volume, weights, 0.5,
                                 mask=None if mask is None else mask[local], data_range=1.0, share=share)
        assert set(terms) == set(full_terms)  # every rank reports every term (same keys for the sum over ranks)
        assert torch.equal(terms["tv_xy"], full_terms["tv_xy"]) and torch.equal(terms["tv_z"], full_terms["tv_z"])
        for k in sums:
            sums[k] += float(terms[k])
        share_total = share_total + loss.detach()
        if loss.requires_grad:
            gp, gv = torch.autograd.grad(loss, (pred, volume), allow_unused=True)
            p_grad += gp
            v_grad += 0 if gv is None else gv
    assert float(share_total) == pytest.approx(float(full.detach()), rel=1e-12)
    for k, v in sums.items():
        assert v == pytest.approx(float(full_terms[k]), rel=1e-12), k
    assert torch.allclose(p_grad, g_pred, rtol=1e-12, atol=1e-15)
    assert torch.allclose(v_grad, g_vol, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("masked", [False, True])
def test_one_share_holding_the_whole_batch_is_the_plain_loss(masked: bool) -> None:
    """The share's denominators are the ones the plain loss uses: float32, bit for bit."""
    pred, target, volume, mask, weights = _loss_inputs(masked)
    pred, target, volume = pred.detach().float(), target.float(), volume.detach().float()
    mask = None if mask is None else mask.float()
    plain, _ = total_loss(pred, target, volume, weights, 0.5, mask=mask, data_range=1.0)
    share = BatchShare.of_batch(mask, tuple(pred.shape), regularisers=True)
    shared, _ = total_loss(pred, target, volume, weights, 0.5, mask=mask, data_range=1.0, share=share)
    assert float(shared) == pytest.approx(float(plain), rel=2e-7)
    l1_plain = total_loss(pred, target, volume, LossWeights(), 1.0, mask=mask, data_range=1.0)[0]
    l1_share = total_loss(pred, target, volume, LossWeights(), 1.0, mask=mask, data_range=1.0, share=share)[0]
    assert torch.equal(l1_plain, l1_share)


def test_an_empty_share_with_a_zero_mask_sum_gives_zero() -> None:
    empty = torch.zeros(0, 16, 16)
    share = BatchShare.of_batch(torch.zeros(3, 16, 16), (3, 16, 16), regularisers=False)
    loss, terms = total_loss(empty, empty, torch.zeros(2, 4, 4), LossWeights(ssim=0.5), 0.5,
                             mask=torch.zeros(0, 16, 16), data_range=1.0, share=share)
    assert float(loss) == 0.0 and not loss.requires_grad
    assert all(float(v) == 0.0 for v in terms.values())


# --------------------------------------------------------------------------------------------
# The collectives, on two gloo ranks in this machine (FileStore: no ports)
# --------------------------------------------------------------------------------------------


def _collectives_worker(rank: int, store_path: str, out_dir: str) -> None:
    torch.distributed.init_process_group("gloo", store=torch.distributed.FileStore(store_path, 2), rank=rank, world_size=2)
    try:
        group = distributed.Group(rank=rank, world_size=2, local_rank=rank, backend="gloo", device=torch.device("cpu"))
        shared_a = torch.zeros(2, 3, requires_grad=True)      # gradient on rank 0 only
        shared_b = torch.zeros((), requires_grad=True)        # gradient on no rank
        frozen = torch.zeros(2)                               # not trained: left alone
        rows = torch.zeros(4, 2, requires_grad=True)          # per-source, gradient on rank 1 only
        gains = torch.zeros(4, requires_grad=True)            # per-source, gradient on both
        if rank == 0:
            shared_a.grad = torch.full((2, 3), 1.5)
        else:
            rows.grad = torch.arange(8.0).reshape(4, 2)
        gains.grad = torch.full((4,), float(rank + 1))
        group.reduce_gradients([shared_a, shared_b, frozen], [rows, gains])
        # every image's rows from its owner: rank r holds 10*r+i in its rows, garbage in the others
        table = torch.tensor([[10.0 * (i % 2) + i if i % 2 == rank else -99.0] * 3 for i in range(5)])
        group.share_rows([table, None])
        terms = group.sum_terms({"l1": torch.tensor(0.25 * (rank + 1)), "tv_xy": torch.tensor(7.0)}, ("l1", "l2"))
        torch.save({"shared_a": shared_a.grad, "shared_b": shared_b.grad, "frozen": frozen.grad, "rows": rows.grad,
                    "gains": gains.grad, "table": table, "terms": terms, "any": (group.any(rank == 1), group.any(False))},
                   os.path.join(out_dir, f"rank{rank}.pt"))
    finally:
        torch.distributed.destroy_process_group()


def test_gradient_sum_row_sharing_and_term_sums_on_two_ranks(tmp_path: Path) -> None:
    import torch.multiprocessing as mp

    mp.start_processes(_collectives_worker, args=(str(tmp_path / "store"), str(tmp_path)), nprocs=2, start_method="spawn")
    r0, r1 = (torch.load(tmp_path / f"rank{r}.pt") for r in (0, 1))
    for r in (r0, r1):
        assert torch.equal(r["shared_a"], torch.full((2, 3), 1.5))  # summed over ranks
        assert r["shared_b"] is None and r["frozen"] is None        # no rank had one: Adam will skip it, as in one process
        assert torch.equal(r["table"], torch.tensor([[float(i) + 10 * (i % 2)] * 3 for i in range(5)]))
        assert float(r["terms"]["l1"]) == 0.75 and float(r["terms"]["tv_xy"]) == 7.0
        assert r["any"] == (True, False)
    assert torch.equal(r0["rows"], torch.zeros(4, 2))                 # rank 0 had none: zeros, so Adam steps it
    assert torch.equal(r1["rows"], torch.arange(8.0).reshape(4, 2))   # per-source gradients stay local
    assert torch.equal(r0["gains"], torch.ones(4)) and torch.equal(r1["gains"], torch.full((4,), 2.0))


# --------------------------------------------------------------------------------------------
# Two gloo ranks under torchrun against one process
# --------------------------------------------------------------------------------------------


def _config() -> SolverConfig:
    """Every part of the loss, calibration of sources and global scales from the first stage, coherence masks."""
    return SolverConfig(stages=[StageConfig(2, 4), StageConfig(1, 6)], batch_size=3, snapshot_every=2,
                        coherence="mask", ssim_weight=0.2, tv_xy_weight=1e-3, tv_z_weight=1e-3,
                        l1_ramp_start=0.2, l1_ramp_end=0.8, calibration_from_stage=0,
                        calibrate_pixel_size=True, calibrate_slice_spacing=True,
                        final_stage_min_passes=0)  # the stages as given: short runs, compared to float32 rounding


def _run_group(cmd: list[str], env: dict[str, str], timeout: float) -> subprocess.CompletedProcess:
    """Run ``cmd`` in its own process group; on timeout kill the whole group (torchrun and its workers)."""
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"torchrun did not finish in {timeout} s:\n{out}\n{err}")
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def _torchrun(root: Path, audit: Path, out: Path, *extra: str, fail: str = "") -> subprocess.CompletedProcess:
    """``torchrun --standalone --nproc-per-node 2 audited_fdt.py reconstruct`` of the scene in ``root``."""
    env = dict(os.environ)
    src = str(Path(napari_fdt.__file__).resolve().parents[1])  # the package under test, also in the workers
    env["PYTHONPATH"] = os.pathsep.join([src, env.get("PYTHONPATH", "")])
    env.update(FDT_AUDIT_WATCH=str(root), FDT_AUDIT_DIR=str(audit), FDT_DIST_TIMEOUT_S="60", OMP_NUM_THREADS="1",
               FDT_TEST_FAIL=fail)
    for name in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT", "FDT_DIST_BACKEND"):
        env.pop(name, None)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
           str(TESTS / "audited_fdt.py"), "reconstruct", str(root / "acq"), "--config", str(root / "cfg.json"),
           "--device", "cpu", "--out", str(out), *extra]
    return _run_group(cmd, env, timeout=180)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """One scene (32×32 px, 4 slices, 9 images), reconstructed by one process and by two gloo ranks."""
    root = tmp_path_factory.mktemp("dist")
    sim = tiny_scene(grid=3, seed=1)  # n_background N_BG
    write_acquisition(sim.acquisition, root / "acq")
    _config().save(root / "cfg.json")
    assert main(["reconstruct", str(root / "acq"), "--config", str(root / "cfg.json"), "--device", "cpu",
                 "--out", str(root / "one" / "RI.tif"), "--quiet"]) == 0
    audit = tmp_path_factory.mktemp("audit")  # the audit logs lie outside the watched folder
    out_dir = root / "two"
    proc = _torchrun(root, audit, out_dir / "RI.tif", "--checkpoint-dir", str(out_dir / "checkpoints"))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return root, sim, proc, audit


def _result(folder: Path):
    ri, _ = read_volume_tiff(folder / "RI.tif")
    report = json.loads((folder / "RI.json").read_text())
    cal = report["calibration"]
    return ri - N_BG, np.array(cal["sources_um"]), np.array(cal["gains"]), cal, report


def test_two_gloo_ranks_give_the_single_process_result(runs) -> None:
    root, sim, _, audit = runs
    dn1, src1, gain1, cal1, _ = _result(root / "one")
    dn2, src2, gain2, cal2, report = _result(root / "two")
    assert report["distributed"]["world_size"] == 2 and report["distributed"]["backend"] == "gloo"
    assert np.abs(dn1).max() > 0.01 and np.abs(src1 - sim.acquisition.sources_um).max() > 0.05  # it did move
    assert np.abs(dn2 - dn1).max() <= DN_TOL
    assert np.abs(src2 - src1).max() <= SOURCES_TOL_UM
    assert np.abs(gain2 / gain1 - 1).max() <= GAIN_RTOL
    assert cal2["pixel_size_um"] == pytest.approx(cal1["pixel_size_um"], rel=GAIN_RTOL)
    assert cal2["slice_spacing_um"] == pytest.approx(cal1["slice_spacing_um"], rel=GAIN_RTOL)
    assert cal2["source_depth_offset_um"] == pytest.approx(cal1["source_depth_offset_um"], abs=SOURCES_TOL_UM)
    # every batch was split between the ranks, and some gave a rank no image (it still joined every collective)
    sizes = [[int(n) for n in (audit / f"rank{r}_batches.txt").read_text().split()] for r in (0, 1)]
    assert len(sizes[0]) == len(sizes[1]) == _config().total_iterations
    assert all(a + b == _config().batch_size for a, b in zip(*sizes))
    assert 0 in sizes[0] and 0 in sizes[1]


def test_only_rank_0_writes_and_prints(runs) -> None:
    root, _, proc, audit = runs
    log0 = (audit / "rank0.txt").read_text()
    log1 = (audit / "rank1.txt").read_text()
    two = root / "two"
    for expected in (two / "RI.tif", two / "RI.json", two / "checkpoints" / "stage_0.pt", two / "checkpoints" / "stage_1.pt"):
        assert f"os.rename {expected.resolve()}" in log0  # the audit sees rank 0's atomic writes...
    assert log1 == ""                                      # ...and no write at all by rank 1
    assert sorted(p.name for p in two.iterdir()) == ["RI.json", "RI.tif", "checkpoints"]
    # one progress report per stage end: rank 0's (the bar writes "stage K/2 (xF) complete")
    assert proc.stdout.count("wrote ") == 1 and proc.stderr.count(") complete") == 2


def test_a_distributed_checkpoint_resumes_in_one_process(runs, tmp_path: Path) -> None:
    """Stage 0's checkpoint holds every rank's source rows and their Adam moments: one process continues the run."""
    root, _, _, _ = runs
    out = tmp_path / "RI.tif"
    assert main(["reconstruct", str(root / "acq"), "--out", str(out), "--resume", str(root / "two" / "checkpoints" / "stage_0.pt"),
                 "--device", "cpu", "--quiet"]) == 0
    dn1, src1, gain1, _, _ = _result(root / "one")
    dn3, src3, gain3, _, _ = _result(tmp_path)
    assert np.abs(dn3 - dn1).max() <= DN_TOL
    assert np.abs(src3 - src1).max() <= SOURCES_TOL_UM
    assert np.abs(gain3 / gain1 - 1).max() <= GAIN_RTOL


def test_a_rank_failing_mid_run_ends_the_launch_without_output(runs, tmp_path: Path) -> None:
    """Rank 1 raises at its third prediction: rank 0, waiting in the gradient sum, fails too (no hang), nothing is written."""
    root, _, _, _ = runs
    proc = _torchrun(root, tmp_path, root / "failed" / "RI.tif", "--quiet", fail="1:3")
    assert proc.returncode != 0
    assert "injected failure on rank 1" in proc.stderr
    assert not (root / "failed").exists()


# --------------------------------------------------------------------------------------------
# Every configuration a single run accepts (issue 46): ranks 2 and 3, batch 1, 2, 4 and the default, validation on and
# off, the model parts and the TV weight fixed or chosen by the data, in a pairwise design (every pair of two settings'
# values is run once: 8 launches)
# --------------------------------------------------------------------------------------------

#: (ranks, batch_size (None: the default), validation, auto): every pair of values of two settings appears.
MATRIX = [(2, 1, True, True), (3, 1, False, False), (2, 2, False, True), (3, 2, True, False),
          (2, 4, True, False), (3, 4, False, True), (2, None, False, False), (3, None, True, True)]
#: How much more than one float32 ulp of noise in its predictions moves the single process a distributed run may differ by.
ULP_FACTOR = 3.0


def _matrix_config(batch: int | None, validation: bool, auto: bool) -> SolverConfig:
    """Short stages on the 16-image scene; ``auto``: the defaults (TV weights and model parts chosen by the data: the TV
    trials, the pupil's pilot, the coarse stage's and the finest stage's tests), else fixed weights and parts."""
    kw: dict = dict(stages=[StageConfig(2, 4), StageConfig(1, 6)], snapshot_every=2, final_stage_min_passes=0,
                    validation_fraction=0.2 if validation else 0.0, checkpoint_every_s=0.0)
    if batch is not None:
        kw["batch_size"] = batch
    if not auto:
        kw.update(tv_xy_weight=1e-3, tv_z_weight=1e-3, calibrate_pupil=False, calibrate_aberrations=False,
                  obliquity_correction=False, sub_slices=1, coherence="mask", field_oversampling=1, pixel_integration=False)
    return SolverConfig(**kw)


def _single(acq, config: SolverConfig, noise_seed: int | None = None) -> dict:
    """The single process's result; with ``noise_seed`` its predictions carry relative noise of 2^-24 (one float32 ulp)."""
    from napari_fdt.recon.run.solver import Reconstructor

    rec = Reconstructor(acq, config, device="cpu")
    if noise_seed is not None:
        g = torch.Generator().manual_seed(noise_seed)
        predict = rec._predict_normalised

        def perturbed(*args, **kwargs):
            p = predict(*args, **kwargs)
            return p * (1 + 2.0 ** -24 * torch.randn(p.shape, generator=g, dtype=p.dtype))

        rec._predict_normalised = perturbed
    for _ in rec.run():
        pass
    return {"dn": rec.delta_n_full(), "sources": rec.sources_um(), "gains": rec.gains(),
            "tv": None if rec.tv_choice is None else [rec.tv_choice.tv_xy_weight, rec.tv_choice.tv_z_weight],
            "parts": dict(rec.parts), "trials": None if rec.parts_choice is None else len(rec.parts_choice.trials),
            "validation": rec.stages[-1].validation_error}


def _gaps(a: dict, b: dict) -> np.ndarray:
    """max |ΔΔn|, max |Δ source| µm, max relative Δ gain."""
    return np.array([np.abs(a["dn"] - b["dn"]).max(), np.abs(a["sources"] - b["sources"]).max(),
                     np.abs(a["gains"] / b["gains"] - 1).max()])


@pytest.fixture(scope="module")
def scene16_dir(tmp_path_factory, scene16):
    return write_acquisition(scene16.acquisition, tmp_path_factory.mktemp("dist16") / "acq")


def _launch_env() -> dict[str, str]:
    """The environment of a ``torchrun`` launch of the package under test: its ``src`` first on the path, one thread
    per rank, torchrun's own variables (from an outer launch) removed."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(Path(napari_fdt.__file__).resolve().parents[1]), env.get("PYTHONPATH", "")])
    env.update(OMP_NUM_THREADS="1", FDT_DIST_TIMEOUT_S="60")
    for name in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT", "FDT_DIST_BACKEND"):
        env.pop(name, None)
    return env


@pytest.mark.parametrize("ranks,batch,validation,auto", MATRIX)
def test_every_configuration_runs_distributed_and_agrees_with_one_process(scene16_dir: Path, tmp_path: Path, ranks: int,
                                                                         batch: int | None, validation: bool, auto: bool) -> None:
    """The launch completes (every rank joins every collective, also with none of a batch's images or only held-out ones,
    in the TV trials, the parts' tests and the pilot, snapshots and in-stage checkpoints) and ends where one process
    ends: the same choices, and Δn, sources and gains within the floor of the two-rank test above or within
    :data:`ULP_FACTOR` times what one float32 ulp of noise moves the single process by (runs whose Adam steps amplify
    rounding, docs/distributed.md)."""
    from napari_fdt import read_acquisition

    config = _matrix_config(batch, validation, auto)
    config.save(tmp_path / "cfg.json")
    env = _launch_env()
    out = tmp_path / "RI.tif"
    proc = _run_group([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", str(ranks),
                       "-m", "napari_fdt", "reconstruct", str(scene16_dir), "--config", str(tmp_path / "cfg.json"),
                       "--device", "cpu", "--out", str(out), "--checkpoint-dir", str(tmp_path / "ck"), "--quiet"], env, timeout=240)
    assert proc.returncode == 0, proc.stderr[-4000:]
    ri, _ = read_volume_tiff(out)
    report = json.loads((tmp_path / "RI.json").read_text())
    cal = report["calibration"]
    dist = {"dn": ri - N_BG, "sources": np.array(cal["sources_um"]), "gains": np.array(cal["gains"])}
    assert report["distributed"]["world_size"] == ranks
    acq = read_acquisition(scene16_dir)
    one = _single(acq, config)
    # the same choices, made on the same numbers
    assert (report["regularisation"]["tv_xy_weight"], report["regularisation"]["tv_z_weight"]) == (
        tuple(one["tv"]) if one["tv"] else (config.tv_xy_weight, config.tv_z_weight))
    assert report["model_parts"]["parts"] == one["parts"]
    chosen = report["model_parts"]["chosen"]  # the same tests ran (the pilot, the coarse stage's end, the finest stage's)
    assert (0 if chosen is None else len(chosen["trials"])) == (one["trials"] or 0)
    if validation:
        assert report["validation"]["error"] == pytest.approx(one["validation"], rel=1e-3)
    ulp = np.max([_gaps(_single(acq, config, noise_seed=s), one) for s in (1, 2)], axis=0)
    floor = np.array([DN_TOL, SOURCES_TOL_UM, GAIN_RTOL])
    assert np.all(_gaps(dist, one) <= np.maximum(floor, ULP_FACTOR * ulp)), (_gaps(dist, one), ulp)
    assert sorted(p.name for p in (tmp_path / "ck").glob("stage_*.pt")) == ["stage_0.pt", "stage_1.pt"]


def test_a_family_runs_distributed_and_agrees_with_one_process(scene16_dir: Path, tmp_path: Path) -> None:
    """``--tv-family`` under two gloo ranks (issue 47): every member a distributed run, the verdict made on the held-out
    errors summed over the ranks, rank 0 writing the members, the pick and the family's checkpoints; the same members
    (the same choices, Δn within the floor above or :data:`ULP_FACTOR` times one float32 ulp's effect) and the same pick
    as the family in one process."""
    from napari_fdt import read_acquisition
    from napari_fdt.cli.family import member_path
    from napari_fdt.recon.run.family import FAMILY_TAUS, member_config, run_family

    config = _matrix_config(None, True, True)
    config.save(tmp_path / "cfg.json")
    env = _launch_env()
    out = tmp_path / "two" / "RI.tif"
    proc = _run_group([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                       "-m", "napari_fdt", "reconstruct", str(scene16_dir), "--config", str(tmp_path / "cfg.json"),
                       "--device", "cpu", "--out", str(out), "--tv-family", "--checkpoint-dir", str(tmp_path / "ck"), "--quiet"],
                      env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert proc.stdout.count("TV family") == 1  # rank 0's verdict, once
    report = json.loads((tmp_path / "two" / "RI.json").read_text())
    family = report["regularisation"]["family"]
    assert report["distributed"]["world_size"] == 2 and [m["tau"] for m in family] == list(FAMILY_TAUS)
    assert (tmp_path / "ck" / "family.json").is_file() and all((tmp_path / "ck" / f"tv{t:g}" / "stage_1.pt").is_file() for t in FAMILY_TAUS)

    acq = read_acquisition(scene16_dir)
    runs = run_family(acq, config, device="cpu")
    with pytest.raises(StopIteration) as ended:
        while True:
            next(runs)
    one = ended.value.value
    assert [m["picked"] for m in family] == [m.picked for m in one.members]
    floor = np.array([DN_TOL, SOURCES_TOL_UM, GAIN_RTOL])
    for entry, member in zip(family, one.members):
        ri, _ = read_volume_tiff(entry["path"])
        cal = json.loads(Path(entry["path"]).with_suffix(".json").read_text())["calibration"]
        dist = {"dn": ri - N_BG, "sources": np.array(cal["sources_um"]), "gains": np.array(cal["gains"])}
        rec = member.rec
        single = {"dn": rec.delta_n_full(), "sources": rec.sources_um(), "gains": rec.gains()}
        assert Path(entry["path"]) == (out if entry["picked"] else member_path(out, member.tau))
        # what one float32 ulp of noise in the single process's predictions moves the member by (its cold run's)
        noisy = [_single(acq, member_config(config, member.tau), noise_seed=s) for s in (1, 2)]
        ulp = np.max([_gaps(r, single) for r in noisy], axis=0)
        ulp_val = max(abs(r["validation"] / rec.stages[-1].validation_error - 1) for r in noisy)
        assert np.all(_gaps(dist, single) <= np.maximum(floor, ULP_FACTOR * ulp)), (member.tau, _gaps(dist, single), ulp)
        assert entry["validation_error"] == pytest.approx(member.validation_error, rel=max(1e-3, ULP_FACTOR * ulp_val))
