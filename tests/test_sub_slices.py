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
    from napari_fdt.recon.run.solver import Reconstructor
    from napari_fdt.recon.settings.config import SolverConfig, StageConfig

    base = dict(stages=[StageConfig(2, 3), StageConfig(1, 3)], batch_size=4, final_stage_min_passes=0,
                tv_xy_weight=0.0, tv_z_weight=0.0)
    one = Reconstructor(scene16.acquisition, SolverConfig(**base), device="cpu")
    two = Reconstructor(scene16.acquisition, SolverConfig(**base, sub_slices=2), device="cpu")
    assert two._build_stage(1).model.sub_slices == 2 and two.evaluation_stage().model.sub_slices == 2
    assert two.plan.phases[-1].seconds_per_iteration > one.plan.phases[-1].seconds_per_iteration
    list(two.run())
    assert np.isfinite(two.delta_n_full()).all() and two.completed_stages == 2


# -- the "auto" sub-slices part (recon/loop/model_parts.py): tried where the physics says the slices are thick, kept where
# the held-out images show it, and then only the finest stage runs again ----------------------------------------------


def _letters_acquisition(sub_slices: int):
    """A 32², 3-slice letters scene (Δn 0.05 in 2 µm slices at NA 0.8: 0.84 of the depth of field), 25 images made with
    ``sub_slices`` screens per slice."""
    from napari_fdt import simulate, source_grid
    from napari_fdt.sim.phantoms import text_phantom

    o = Optics(**{**OPTICS, "n_slices": 3})
    dn = text_phantom((32, 32), 3, text="UC", delta_n=0.05)
    return simulate(dn, o, source_grid(5, 8.0, 15.0), seed=3, device="cpu", photons=20000.0, sub_slices=sub_slices).acquisition


def _auto_config(**kw):
    from napari_fdt.recon.settings.config import SolverConfig, StageConfig

    base = dict(stages=[StageConfig(2, 10), StageConfig(1, 30)], batch_size=8, snapshot_every=5, validation_fraction=0.25,
                final_stage_min_passes=0, tv_xy_weight=0.0, tv_z_weight=0.0, pixel_integration="false", coherence="none",
                obliquity_correction="false", calibrate_pupil="false", calibrate_aberrations="false", field_oversampling=1)
    return SolverConfig(**{**base, **kw})


def test_auto_sub_slices_are_tried_only_where_the_slices_are_thick_against_the_depth_of_field() -> None:
    """The physics' criterion: slice / (λ/(n_b(1 − cos θ))) ≥ 0.5. At NA 0.8 in water the depth of field is 2.37 µm:
    2 µm slices (0.84) are tried, 1 µm slices (0.42) are thin screens; a number given is taken as set."""
    from types import SimpleNamespace

    from napari_fdt.recon.loop.model_parts import requested_for
    from napari_fdt.recon.settings.config import SolverConfig

    thick, thin = Optics(**OPTICS), Optics(**{**OPTICS, "slice_spacing_um": 1.0})
    assert thick.depth_of_field_um == pytest.approx(0.635 / (1.33 * (1 - np.sqrt(1 - (0.8 / 1.33) ** 2))))
    requested, why = requested_for(SolverConfig(), SimpleNamespace(optics=thick, extra={}))
    assert requested["sub_slices"] is None and why["sub_slices"] == "setting"
    requested, why = requested_for(SolverConfig(), SimpleNamespace(optics=thin, extra={}))
    assert requested["sub_slices"] is False and why["sub_slices"].startswith("physics")
    requested, _ = requested_for(SolverConfig(sub_slices=3), SimpleNamespace(optics=thin, extra={}))
    assert requested["sub_slices"] is True


def test_auto_sub_slices_stay_off_on_data_made_with_one_screen_per_slice() -> None:
    """Through a volume fitted with one screen per slice to data made that way, two screens per slice predict the
    held-out images worse (the volume holds what thin screens need): the trial's paired change is negative, the part
    stays off, and the run is the one without it (one finest stage, one screen per slice)."""
    from napari_fdt.recon.run.solver import Reconstructor

    rec = Reconstructor(_letters_acquisition(1), _auto_config(), device="cpu")
    snaps = list(rec.run())
    choice = rec.parts_choice
    trial = next(t for t in choice.trials if t["part"] == "sub_slices")
    assert not choice.parts["sub_slices"] and choice.chosen_by["sub_slices"] == "validation"
    assert trial["improvement"] < -trial["threshold"] * trial["standard_error"], trial
    assert rec._build_stage(1).model.sub_slices == 1 and len(rec.plan.phases) == 2
    assert all(b.global_iteration > a.global_iteration for a, b in zip(snaps, snaps[1:]))  # nothing ran again


def _forced(monkeypatch, keep: set[int]) -> None:
    """The parts' test with its verdict forced on at the listed calls (1: the first part tried, sub-slices) and off
    elsewhere: the mechanics are under test here, not the test's power."""
    import napari_fdt.recon.choices.parts_search as parts_search

    decide, calls = parts_search.decide, []

    def forced(ref, cand):
        calls.append(1)
        return {**decide(ref, cand), "on": len(calls) in keep}

    monkeypatch.setattr(parts_search, "decide", forced)


def test_kept_sub_slices_run_only_the_finest_stage_again_with_two_screens_per_slice(monkeypatch) -> None:
    """Where the test keeps sub-slices alone, the finest stage runs again from its start with 2 screens per slice (a
    plan phase of its own, priced with them); the coarse stage is not run again (its model has no sub-slices), and the
    parts not kept are tried again at the end, through the volume trained with sub-slices."""
    from napari_fdt.recon.run.report import describe_parts, model_parts_summary
    from napari_fdt.recon.run.solver import Reconstructor

    _forced(monkeypatch, {1})
    rec = Reconstructor(_letters_acquisition(4), _auto_config(obliquity_correction="auto"), device="cpu")
    finest = rec.plan.phases[-1]  # (its iterations: the tests at its end are not run again)
    assert rec.plan.if_finest_parts_kept_s > finest.iterations * finest.seconds_per_iteration
    snaps = list(rec.run())
    choice = rec.parts_choice
    assert choice.parts["sub_slices"] and not choice.parts["obliquity"] and choice.rerun == "finest" and choice.pending == []
    assert [(t["part"], t["pass"]) for t in choice.trials] == [("sub_slices", 1), ("obliquity", 1), ("obliquity", 2)]
    assert choice.trials[-1]["after"] == "finest"
    assert "obliquity (again, finest stage rerun) off" in describe_parts(model_parts_summary(rec))
    assert rec._build_stage(1).model.sub_slices == 2 and rec._build_stage(0).envelope  # the coarse stage unchanged
    assert rec.evaluation_stage().model.sub_slices == 2
    again = rec.plan.phases[-1]
    assert again.parts == ("sub_slices",) and again.stage == 1 and "again with sub_slices" in again.name
    assert again.seconds_per_iteration > rec.plan.phases[-2].seconds_per_iteration
    # the iteration count goes back once, to the finest stage's start, not to the first stage
    back = [i for i in range(1, len(snaps)) if snaps[i].global_iteration < snaps[i - 1].global_iteration]
    assert len(back) == 1 and snaps[back[0]].stage == 1 and all(s.stage == 1 for s in snaps[back[0]:])
    assert np.isfinite(rec.delta_n_full()).all() and rec.completed_stages == 2


def test_a_part_kept_after_the_finest_stage_ran_again_makes_every_stage_run_again_with_all_kept(monkeypatch) -> None:
    """Sub-slices kept first (the finest stage again), then obliquity kept at that stage's end: every stage runs again
    from the first with both (the coarse stage multi-slice with one screen per slice, the finest with 2), and the
    plan's phase of each stage is found as the last of that stage."""
    from napari_fdt.recon.run.solver import Reconstructor

    _forced(monkeypatch, {1, 3})  # calls: sub-slices (1), obliquity (2), obliquity again (3)
    rec = Reconstructor(_letters_acquisition(4), _auto_config(obliquity_correction="auto", parts_backward=False), device="cpu")
    snaps = list(rec.run())
    choice = rec.parts_choice
    assert choice.parts["sub_slices"] and choice.parts["obliquity"] and choice.rerun == "stages"
    assert [(t["part"], t["pass"]) for t in choice.trials] == [("sub_slices", 1), ("obliquity", 1), ("obliquity", 2)]
    assert snaps[-1].rerun_with == ("sub_slices", "obliquity")
    assert rec._build_stage(1).model.sub_slices == 2 and rec._build_stage(0).model.sub_slices == 1
    assert not rec._build_stage(0).envelope
    back = [i for i in range(1, len(snaps)) if snaps[i].global_iteration < snaps[i - 1].global_iteration]
    assert [snaps[i].stage for i in back] == [1, 0]  # the finest stage again, then every stage again
    names = [p.name for p in rec.plan.phases]
    assert names[-3:] == ["stage 2/2 (x1) again with sub_slices", "stage 1/2 (x2) again with sub_slices+obliquity",
                          "stage 2/2 (x1) again with sub_slices+obliquity"]
    assert rec._phase_index == len(rec.plan.phases) - 1
    assert np.isfinite(rec.delta_n_full()).all() and rec.completed_stages == 2


def test_auto_sub_slices_are_not_tried_where_they_would_not_fit_in_memory(monkeypatch) -> None:
    """The run is checked for the model its first pass runs (one screen per slice); where 2 screens per slice would not
    fit, the part is not tried (its reason names the memory) instead of the run being refused."""
    import dataclasses

    import napari_fdt.device as device_module
    from napari_fdt.recon.problem.preflight import finest_stage_bytes
    from napari_fdt.recon.run.solver import Reconstructor

    acq, cfg = _letters_acquisition(1), _auto_config()
    one = finest_stage_bytes(acq, dataclasses.replace(cfg, sub_slices=1), acq.sources_um, 1, "cpu")[0]
    two = finest_stage_bytes(acq, dataclasses.replace(cfg, sub_slices=2), acq.sources_um, 1, "cpu")[0]
    assert two > 1.2 * one  # the stored fields grow with the screens
    monkeypatch.setattr(device_module, "available_bytes", lambda device: int((one + two) / 2 / 0.9))
    rec = Reconstructor(acq, cfg, device="cpu")
    assert "sub_slices" not in rec._auto_parts and rec._parts_chosen_by["sub_slices"].startswith("memory: 2 screens per slice")
    assert rec.plan.if_finest_parts_kept_s is None
    monkeypatch.setattr(device_module, "available_bytes", lambda device: int(2 * two))
    assert "sub_slices" in Reconstructor(acq, cfg, device="cpu")._auto_parts
