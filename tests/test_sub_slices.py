"""Sub-slices (issue 27, item 1): a thick slice crossed in several symmetric steps. Held against the independent
reference (tests/independent_reference.py, float64, written from docs/physics.md), which models a continuous slab
when it is given each slice cut into many sub-slices."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from napari_fdt import Optics
from napari_fdt.errors import FDTInputError
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.physics.grid import plan_for_sources
from tests import independent_reference as ref

# 2 µm slices at NA 0.8: the thin screen ignores diffraction inside each slice (issue 27: ≈ 2 % image error)
OPTICS = dict(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=4, slice_spacing_um=2.0,
              image_plane_um=0.0)


def _scene():
    h = w = 32
    yy, xx = np.mgrid[:h, :w]
    bead = ((yy - 15.5) ** 2 + (xx - 17.0) ** 2 < 7.0**2).astype(np.float64)
    dn = np.stack([0.04 * bead, 0.04 * bead, 0.02 * bead, np.zeros_like(bead)])
    sources = np.array([[0.0, 0.0, 15.0], [3.0, -2.0, 18.0], [-4.0, 3.0, 16.0]])
    return dn, sources


def _reference(dn: np.ndarray, sources: np.ndarray, m: int) -> np.ndarray:
    """The independent reference with each slice cut into ``m`` sub-slices (its screens at their centres)."""
    optics = {**OPTICS, "n_slices": OPTICS["n_slices"] * m, "slice_spacing_um": OPTICS["slice_spacing_um"] / m}
    ri = OPTICS["n_background"] + np.repeat(dn, m, axis=0)
    # the same window as the unrefined plan: it depends on the volume's thickness, which sub-slicing keeps
    return ref.forward_images(optics, ri, sources, np.ones(len(sources)))


def _model(dn: np.ndarray, sources: np.ndarray, n: int) -> np.ndarray:
    o = Optics(**OPTICS)
    model = MultiSliceModel(o, plan_for_sources(o, dn.shape[1:], sources, warn=False), device="cpu", dtype=torch.float64,
                            sub_slices=n)
    with torch.no_grad():
        out = model(torch.from_numpy(dn), torch.from_numpy(sources), torch.ones(len(sources), dtype=torch.float64))
    return out.numpy()


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def test_sub_slices_are_the_reference_scheme_with_that_many_screens() -> None:
    dn, src = _scene()
    for n in (1, 2, 3):
        assert _rel(_model(dn, src, n), _reference(dn, src, n)) < 1e-9, n


def test_sub_slices_converge_to_the_continuous_slab_as_one_over_n_squared() -> None:
    dn, src = _scene()
    slab = _reference(dn, src, 16)  # converged: a further halving changes it by ~1/4 of the m=8 error
    err = {n: _rel(_model(dn, src, n), slab) for n in (1, 2, 4)}
    print({n: f"{e:.2e}" for n, e in err.items()})
    assert err[1] > 5e-3  # the thin screen is visibly off on 2 µm slices
    assert 3.0 < err[1] / err[2] < 5.5 and 3.0 < err[2] / err[4] < 5.5  # second order in the step
    assert err[4] < err[1] / 10


def test_gradients_flow_through_the_sub_slices() -> None:
    dn, src = _scene()
    o = Optics(**OPTICS)
    model = MultiSliceModel(o, plan_for_sources(o, dn.shape[1:], src, warn=False), device="cpu", dtype=torch.float64,
                            sub_slices=2, backward_mode="autograd")
    x = torch.from_numpy(dn).requires_grad_()
    model(x, torch.from_numpy(src), torch.ones(3, dtype=torch.float64)).square().sum().backward()
    stored = MultiSliceModel(o, plan_for_sources(o, dn.shape[1:], src, warn=False), device="cpu", dtype=torch.float64,
                             sub_slices=2, backward_mode="stored")
    y = torch.from_numpy(dn).requires_grad_()
    stored(y, torch.from_numpy(src), torch.ones(3, dtype=torch.float64)).square().sum().backward()
    assert torch.allclose(x.grad, y.grad, rtol=1e-9, atol=1e-12) and float(x.grad.abs().max()) > 0


@pytest.mark.parametrize("bad", [0, 1.5, True, -2])
def test_sub_slices_must_be_a_whole_number(bad) -> None:
    dn, src = _scene()
    o = Optics(**OPTICS)
    with pytest.raises(FDTInputError) as err:
        MultiSliceModel(o, plan_for_sources(o, dn.shape[1:], src, warn=False), device="cpu", sub_slices=bad)
    assert err.value.field == "sub_slices"


def test_fdt_simulate_forward_accuracy_high_makes_the_sub_sliced_images(tmp_path) -> None:
    """`fdt simulate --forward-accuracy high` renders with 4 screens per slice on a field grid twice as fine: its
    noise-free images are the independent reference's with each slice cut in 4 and the RI interpolated onto the fine
    grid (read with tifffile and json only), and it says so."""
    import json
    import subprocess
    import sys

    import tifffile

    out = tmp_path / "high"
    subprocess.run([sys.executable, "-m", "napari_fdt", "simulate", "beads", str(out), "--shape", "32", "32",
                    "--n-slices", "4", "--sources", "2", "--depth-um", "15", "--no-noise", "--forward-accuracy", "high"],
                   check=True, capture_output=True, timeout=300)
    meta = json.loads((out / "acquisition.json").read_text())
    truth = json.loads((out / "ground_truth_sources_um.json").read_text())
    assert meta["simulated"]["sub_slices"] == 4 and meta["simulated"]["field_oversampling"] == 2
    ri = np.asarray(tifffile.imread(out / "ground_truth_ri.tif"), dtype=np.float64)
    images = np.asarray(tifffile.imread(out / meta["images"]), dtype=np.float64)
    optics = {k: meta[k] for k in ("wavelength_um", "n_background", "na", "pixel_size_um", "n_slices", "slice_spacing_um",
                                   "image_plane_um")}
    fine = {**optics, "n_slices": 4 * optics["n_slices"], "slice_spacing_um": optics["slice_spacing_um"] / 4,
            "pixel_size_um": optics["pixel_size_um"] / 2}
    dn = np.repeat(ri, 4, axis=0) - optics["n_background"]
    for axis in (1, 2):  # the fine grid: the samples, and the mean of neighbours between (background beyond the image)
        nxt = np.concatenate([np.delete(dn, 0, axis=axis), np.zeros_like(np.take(dn, [0], axis=axis))], axis=axis)
        dn = np.stack([dn, (dn + nxt) / 2], axis=axis + 1).reshape(*[2 * n if a == axis else n for a, n in enumerate(dn.shape)])
    win = ref.plan_window(optics, ri.shape[1:], np.asarray(truth["sources_um"]))  # the camera grid's window, in µm
    win = {k: 2 * v for k, v in win.items()}
    expected = ref.forward_images(fine, optics["n_background"] + dn, truth["sources_um"], truth["gain"], window=win)[:, ::2, ::2]
    thin = ref.forward_images(optics, ri, truth["sources_um"], truth["gain"])
    assert _rel(images, expected) < 1e-4 < _rel(images, thin)


def test_the_solver_runs_its_multi_slice_stages_with_the_setting(scene16) -> None:
    """`sub_slices` reaches the multi-slice stages (not the envelope ones), the plan prices its screens, and a short
    run stays finite."""
    from napari_fdt.recon.config import SolverConfig, StageConfig
    from napari_fdt.recon.solver import Reconstructor

    base = dict(stages=[StageConfig(2, 3), StageConfig(1, 3)], batch_size=4, final_stage_min_passes=0,
                tv_xy_weight=0.0, tv_z_weight=0.0)
    one = Reconstructor(scene16.acquisition, SolverConfig(**base), device="cpu")
    two = Reconstructor(scene16.acquisition, SolverConfig(**base, sub_slices=2), device="cpu")
    assert two._build_stage(1).model.sub_slices == 2 and two.evaluation_stage().model.sub_slices == 2
    assert two.plan.phases[-1].seconds_per_iteration > one.plan.phases[-1].seconds_per_iteration
    list(two.run())
    assert np.isfinite(two.delta_n_full()).all() and two.completed_stages == 2
