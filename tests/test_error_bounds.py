"""The per-voxel error bound (issue 50): the raw score against hand-computed statistics, split conformal against its
order statistic, the noise model against noise with a known variance, the replicates' settings and start, and
``fdt reconstruct --error-bounds`` / ``fdt plan --error-bounds`` end to end on the tests' scene."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from napari_fdt.recon.assess.bounds import REPLICATES, BoundCalibration, bound, conformal_quantile, raw_score
from napari_fdt.recon.run.error_bounds import noise_model, replicate_images


def test_raw_score_is_the_replicates_bias_plus_spread_then_the_neighbourhood_max() -> None:
    rng = np.random.default_rng(0)
    result = rng.uniform(0, 0.02, (4, 9, 9))
    reps = np.stack([result + 0.003, result + 0.001])  # bias 0.002 everywhere, spread std(ddof=1) of (0.003, 0.001)
    s = raw_score(result, reps, slices=1, pixels=1, alpha=0.0)
    np.testing.assert_allclose(s, 0.002 + np.std([0.003, 0.001], ddof=1) + 1e-6, rtol=1e-9)
    # one voxel's bias spreads over its 3 × 5 × 5 neighbourhood and no further; the contrast term adds α·max|R| there
    reps = np.repeat(result[None], 2, axis=0)
    reps[:, 2, 4, 4] += 0.01
    s = raw_score(result, reps, slices=3, pixels=5, alpha=0.0)
    assert s[1:4, 2:7, 2:7] == pytest.approx(0.01 + 1e-6)
    assert s[0, 4, 4] == pytest.approx(1e-6) and s[2, 1, 4] == pytest.approx(1e-6) and s[2, 4, 7] == pytest.approx(1e-6)
    flat = np.zeros((3, 8, 8))
    flat[1, 3, 3] = 0.05
    s = raw_score(flat, np.repeat(flat[None], 2, axis=0), slices=1, pixels=3, alpha=0.2)
    assert s[1, 2, 4] == pytest.approx(0.2 * 0.05 + 1e-6) and s[1, 5, 5] == pytest.approx(1e-6)
    c = BoundCalibration(slices=1, pixels=3, alpha=0.2, deflate=False, q=2.5, level=0.9, scenes=1, source="test")
    np.testing.assert_allclose(bound(flat, np.repeat(flat[None], 2, axis=0), c), 2.5 * s, rtol=1e-6)
    with pytest.raises(ValueError, match="replicates must be"):
        raw_score(flat, flat, slices=1, pixels=1, alpha=0.0)


def test_conformal_quantile_is_the_order_statistic_and_covers_new_draws() -> None:
    ratios = np.arange(1, 100, dtype=float)  # n = 99: ⌈100 · 0.9⌉ = 90th smallest
    assert conformal_quantile(ratios, 0.9) == 90.0
    rng = np.random.default_rng(1)
    q = conformal_quantile(rng.exponential(size=2000), 0.9)
    fresh = rng.exponential(size=200_000)
    assert 0.88 <= float((fresh <= q).mean()) <= 0.92  # exchangeable draws: coverage ≥ 0.9, and not much above


def test_noise_model_recovers_shot_noise_and_a_floor() -> None:
    rng = np.random.default_rng(2)
    pred = rng.uniform(10, 2000, (40, 32, 32))
    a, b = 1.6, 200.0
    images = pred + np.sqrt(a * pred + b) * rng.standard_normal(pred.shape)
    fa, fb = noise_model(images, pred)
    assert fa == pytest.approx(a, rel=0.05) and fb == pytest.approx(b, rel=0.15)
    # the replicates' noise has the fitted variance
    again = replicate_images(pred, (fa, fb), rng) - pred
    assert float(np.var(again / np.sqrt(fa * pred + fb))) == pytest.approx(1.0, rel=0.02)
    # a stack larger than the sample the fit reads gives the same figures from evenly spaced whole images
    from napari_fdt.recon.run import error_bounds as eb

    small = eb.NOISE_SAMPLE_PIXELS
    try:
        eb.NOISE_SAMPLE_PIXELS = 10 * 32 * 32
        sa, sb = noise_model(images, pred)
    finally:
        eb.NOISE_SAMPLE_PIXELS = small
    assert sa == pytest.approx(a, rel=0.1) and sb == pytest.approx(b, rel=0.3)
    # noise without shot noise: a flat variance, no negative slope
    flat = pred + 5.0 * rng.standard_normal(pred.shape)
    fa, fb = noise_model(flat, pred)
    assert fa >= 0 and fa * 2500 + fb == pytest.approx(25.0, rel=0.15)


def test_replicates_start_where_the_run_started_with_its_choices_fixed(scene16, monkeypatch) -> None:
    """Each replicate: the run's predictions plus noise, the run's own start positions, its TV weights and parts fixed."""
    import napari_fdt as fdt
    from napari_fdt.recon.run import error_bounds as eb
    from napari_fdt.recon.run.solver import Reconstructor

    cfg = fdt.SolverConfig(stages=[{"factor": 2, "iterations": 4}, {"factor": 1, "iterations": 4}], batch_size=4,
                           final_stage_min_passes=1, error_bounds=True)
    rec = Reconstructor(scene16.acquisition, cfg, device="cpu")
    for _ in rec.run():
        pass
    made = []
    real_init = Reconstructor.__init__

    def spy(self, acquisition, config=None, *, initial_sources_um=None, **kw):
        made.append((acquisition, config, np.array(initial_sources_um)))
        real_init(self, acquisition, config, initial_sources_um=initial_sources_um, **kw)

    monkeypatch.setattr(Reconstructor, "__init__", spy)
    out = eb.error_bounds(rec)
    assert out is not None and len(made) == REPLICATES
    assert out.bound.shape == rec.delta_n_full().shape and np.all(out.bound > 0) and np.all(np.isfinite(out.bound))
    for acq, config, start in made:
        np.testing.assert_array_equal(start, rec.initial_sources_um)
        assert config.tv_xy_weight == rec.loss_weights.tv_xy and not config.error_bounds and not config.half_set_resolution
        assert acq.images.shape == scene16.acquisition.images.shape
        np.testing.assert_array_equal(acq.sources_um, scene16.acquisition.sources_um)
    first, second = made[0][0].images, made[1][0].images
    assert not np.array_equal(first, second) and not np.array_equal(first, scene16.acquisition.images)  # fresh noise


def _fdt(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "napari_fdt", *args], capture_output=True, text=True)


def test_cli_writes_the_bound_beside_the_result_and_its_report_section(tiny_dir: Path, tmp_path: Path) -> None:
    settings = tmp_path / "short.json"
    settings.write_text(json.dumps({"stages": [{"factor": 2, "iterations": 6}, {"factor": 1, "iterations": 6}],
                                    "batch_size": 4, "final_stage_min_passes": 1}))
    out = tmp_path / "res" / "RI.tif"
    done = _fdt("reconstruct", str(tiny_dir), "--out", str(out), "--config", str(settings), "--error-bounds", "--quiet",
                "--device", "cpu")
    assert done.returncode == 0, done.stderr
    from napari_fdt.data.volumes import read_volume

    ri, voxel = read_volume(out)
    bound_vol, bound_voxel = read_volume(out.with_name("RI_bounds.tif"))
    assert bound_vol.shape == ri.shape and bound_voxel == pytest.approx(voxel) and np.all(bound_vol > 0)
    report = json.loads(out.with_name("RI.json").read_text())
    section = report["error_bounds"]
    assert Path(section["path"]) == out.with_name("RI_bounds.tif") and section["level"] == 0.9
    assert section["replicates"] == REPLICATES and section["mean_bound"] == pytest.approx(float(bound_vol.mean()), rel=1e-5)
    assert "error bound:" in done.stdout
    # the bound would be replaced: refused before the run without --overwrite
    out.unlink()
    out.with_name("RI.json").unlink()
    again = _fdt("reconstruct", str(tiny_dir), "--out", str(out), "--config", str(settings), "--error-bounds", "--quiet")
    assert again.returncode == 2 and "RI_bounds.tif exists" in again.stderr and not out.exists()


def test_plan_prices_the_bound_as_its_replicates_stages(tiny_dir: Path) -> None:
    from napari_fdt import read_acquisition
    from napari_fdt.recon.loop.plan import RUN, plan_for
    from napari_fdt.recon.settings.config import SolverConfig

    acq = read_acquisition(tiny_dir)
    cfg = SolverConfig(stages=[{"factor": 2, "iterations": 30}, {"factor": 1, "iterations": 30}], tv_xy_weight=1.0,
                       tv_z_weight=0.5, error_bounds=True)
    plan, _ = plan_for(acq, cfg, "cpu")
    without, _ = plan_for(acq, dataclasses.replace(cfg, error_bounds=False), "cpu")
    assert without.bounds_s is None
    # fixed weights and no parts to choose here: the run's phases are the stages, and each replicate runs them again
    assert plan.bounds_s == pytest.approx(REPLICATES * sum(p.predicted_s for p in without.phases if p.pass_name == RUN), rel=1e-6)
    assert "then the error bound" in plan.summary() and plan.to_dict()["predicted_extra_s_error_bounds"] == plan.bounds_s


def test_a_data_parallel_launch_with_the_bound_is_refused_before_the_run(tiny_dir: Path, tmp_path: Path, monkeypatch,
                                                                          capsys) -> None:
    """Under torchrun the bound would be skipped (it is made in one process): refused with the fix, nothing written."""
    from napari_fdt.cli import main

    for name, value in {"WORLD_SIZE": "2", "RANK": "0", "LOCAL_RANK": "0", "LOCAL_WORLD_SIZE": "2"}.items():
        monkeypatch.setenv(name, value)
    out = tmp_path / "RI.tif"
    assert main(["reconstruct", str(tiny_dir), "--out", str(out), "--error-bounds", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "error_bounds: is made in one process" in err and "--config RI.json --error-bounds" in err
    assert not out.exists() and not out.with_name("RI_bounds.tif").exists()
