"""The branch trial of the parts that change what the volume must be (issue 49; recon/choices/parts_branch.py): sub-slices
that the trial through the volume cannot see are kept by a short branch of training where the data were made with
them, and rejected, with the run unchanged, where they were not."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_parts_backward import _acquisition, _config

from napari_fdt.recon.loop.model_parts import BRANCH_MIN_ITERATIONS, branch_iterations
from napari_fdt.recon.run.solver import Reconstructor


@pytest.fixture(scope="module")
def thick_data():
    """The 3-slice letters scene made with 4 screens per 2 µm slice (0.84 of the depth of field: thick by the criterion)."""
    return _acquisition(sub_slices=4)


def _run(acq, **kw) -> Reconstructor:
    rec = Reconstructor(acq, _config(sub_slices="auto", **kw), device="cpu")
    for _ in rec.run():
        pass
    return rec


def test_sub_slices_the_data_have_are_kept_by_a_branch_where_the_volume_hides_them(thick_data) -> None:
    """Data made with 4 screens per slice: through the volume trained with one screen, sub-slices do not look better (the
    volume adapted to thin screens); the branch trains both models for the same iterations from the same state and the
    held-out images favour sub-slices beyond Student's threshold. Every stage runs again with them (multi-slice coarse
    stages: the volume the thin model made differs from the coarse stages on), and the run ends with held-out images
    better than the run without branches (the same scene, seed and schedule)."""
    rec = _run(thick_data)
    trials = [t for t in rec.parts_choice.trials if t["part"] == "sub_slices"]
    assert [t.get("test") for t in trials] == [None, "branch"]
    through, branch = trials
    assert not through["on"] and branch["on"] and rec.parts["sub_slices"] and rec.parts_choice.rerun == "stages"
    assert branch["iterations"] == branch_iterations(30) == BRANCH_MIN_ITERATIONS
    # the verdict is the admission's rule on the two arms' held-out errors (the arm without the part the reference)
    d = np.asarray(branch["image_errors_without"]) - np.asarray(branch["image_errors"])
    assert branch["improvement"] == pytest.approx(d.mean())
    assert branch["improvement"] > branch["threshold"] * d.std(ddof=1) / np.sqrt(d.size)
    assert branch["improvement"] > 0.01 * np.mean(branch["image_errors_without"])
    without = _run(thick_data, parts_branch=False)
    assert not without.parts["sub_slices"]
    assert rec.stages[-1].validation_error < 0.95 * without.stages[-1].validation_error


def test_a_part_kept_by_a_branch_sends_the_other_parts_to_the_stage_run_again(thick_data) -> None:
    """Physics first: once the branch keeps sub-slices, the parts that can absorb any residual (here the aberrations) are
    not tried through the thin screens' volume; they are tried at the end of the second pass, trained with sub-slices."""
    rec = _run(thick_data)
    finest = [t for t in rec.parts_choice.trials if "at_stage" not in t]
    parts = [(t["part"], t.get("pass")) for t in finest]
    assert parts == [("sub_slices", 1), ("sub_slices", 1), ("aberrations", 2)]
    assert finest[-1]["after"] == "stages" and rec.parts_choice.pending == []


def test_a_branch_that_rejects_leaves_the_run_as_it_was(monkeypatch) -> None:
    """The branch forced on data made with one screen per slice: it finds sub-slices worse, and the run (volume, sources,
    gains, held-out error) is the same to the bit as without branches: both arms start from a copy of the state and it
    is restored."""
    import napari_fdt.recon.choices.parts_search as parts_search

    acq = _acquisition()
    monkeypatch.setattr(parts_search, "branch_due", lambda rec, part: part == "sub_slices")
    rec = _run(acq)
    monkeypatch.undo()
    plain = _run(acq, parts_branch=False)
    (branch,) = [t for t in rec.parts_choice.trials if t.get("test") == "branch"]
    assert not branch["on"] and branch["improvement"] < 0 and not rec.parts["sub_slices"]
    assert torch.equal(rec.volume.x, plain.volume.x)
    assert np.array_equal(rec.sources_um(), plain.sources_um()) and np.array_equal(rec.gains(), plain.gains())
    assert rec.stages[-1].validation_error == plain.stages[-1].validation_error


def test_the_plan_prices_the_branch() -> None:
    """The plan's test at the finest stage's end adds both arms' iterations (at the finest stage's price without and with
    sub-slices) and their held-out predictions where the branch may run, and nothing without it."""
    from napari_fdt.recon.loop.parts_price import PREDICT_SHARE, TRIAL_SETUP_S
    from napari_fdt.recon.loop.plan import plan_for

    acq = _acquisition()
    on, _ = plan_for(acq, _config(sub_slices="auto"), "cpu")
    off, _ = plan_for(acq, _config(sub_slices="auto", parts_branch=False), "cpu")
    (fin_on,) = [p for p in on.phases if p.test_s and p.stage == 1]
    (fin_off,) = [p for p in off.phases if p.test_s and p.stage == 1]
    plain, _ = plan_for(acq, _config(sub_slices=1), "cpu")
    with_sub, _ = plan_for(acq, _config(sub_slices=2), "cpu")
    assert with_sub.phases[-1].seconds_per_iteration > plain.phases[-1].seconds_per_iteration
    batch, n_held = 8, len(Reconstructor(acq, _config(), device="cpu").validation_indices)
    per_image = (plain.phases[-1].seconds_per_iteration + with_sub.phases[-1].seconds_per_iteration) / batch
    expected = (branch_iterations(30) * batch + n_held * PREDICT_SHARE) * per_image + TRIAL_SETUP_S["cpu"]
    assert fin_on.test_s - fin_off.test_s == pytest.approx(expected, rel=1e-6)
