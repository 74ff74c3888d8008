"""The pupil chosen before the stages from a pilot at Δn = 0 (:mod:`napari_fdt.recon.choices.parts_pilot`)."""

from __future__ import annotations

import numpy as np
import pytest

from napari_fdt.recon.choices import parts_pilot
from napari_fdt.recon.loop.model_parts import PILOT_ITERATIONS
from napari_fdt.recon.loop.phases import PUPIL_PILOT
from napari_fdt.recon.loop.plan import RERUN
from napari_fdt.recon.run.report import describe_parts, model_parts_summary
from napari_fdt.recon.run.solver import Reconstructor
from napari_fdt.recon.settings.config import SolverConfig, StageConfig


@pytest.fixture(scope="module")
def soft_pupil():
    """The 32×32, 3-slice letters scene of the model-parts tests (25 noisy images) through the pupil the solver's model
    assumes (edge 0.03), which its files do not state: the pupil is an "auto" part the images do not need."""
    from napari_fdt import Optics, simulate, source_grid
    from napari_fdt.sim.phantoms import text_phantom

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=3,
               slice_spacing_um=2.0, image_plane_um=0.0)
    sim = simulate(text_phantom((32, 32), 3, text="UC", delta_n=0.04), o, source_grid(5, 8.0, 15.0), seed=3, device="cpu",
                   photons=5000.0, pupil_edge=0.03)
    acq = sim.acquisition
    acq.extra.pop("pupil_edge")
    return acq


def _config(**kw) -> SolverConfig:
    base = dict(stages=[StageConfig(2, 10), StageConfig(1, 30)], batch_size=8, snapshot_every=5, validation_fraction=0.25,
                tv_xy_weight=0.0, tv_z_weight=0.0, pixel_integration="false", coherence="none", obliquity_correction="false",
                calibrate_aberrations="false", sub_slices=1, field_oversampling=1)
    base.update(kw)
    return SolverConfig(**base)


def _run(acq, cfg) -> tuple[Reconstructor, list]:
    rec = Reconstructor(acq, cfg, device="cpu")
    return rec, list(rec.run())


def test_a_pilot_that_keeps_nothing_leaves_the_run_as_it_was(soft_pupil) -> None:
    """The images need no pupil part: the pilot keeps none, and since it sets back everything it trained, the run is
    the run without a pilot to the bit; its trial comes first in the record (pass 0)."""
    with_pilot, snaps = _run(soft_pupil, _config())
    without, _ = _run(soft_pupil, _config(parts_pilot=False))
    choice = with_pilot.parts_choice
    first = choice.trials[0]
    assert first["part"] == "pupil" and first["pass"] == 0 and not first["on"], first
    assert first["reference_error"] > 0 and len(first["image_errors"]) == len(with_pilot.validation_indices)
    assert choice.rerun is None and not choice.parts["pupil"]
    assert np.array_equal(with_pilot.delta_n_full(), without.delta_n_full())
    rest = [(t["part"], t["on"], t["validation_error"]) for t in choice.trials[1:]]
    assert rest == [(t["part"], t["on"], t["validation_error"]) for t in without.parts_choice.trials]
    assert choice.seconds > without.parts_choice.seconds  # the pilot's time is the choice's
    # ... and not the first stage's iterations': its seconds per iteration leave the pilot out
    assert with_pilot.stages[0].choice_s >= with_pilot.early_trials.seconds > 0 == without.stages[0].choice_s
    assert "pupil (before the stages, at Δn = 0) off" in describe_parts(model_parts_summary(with_pilot))
    # the pilot is the plan's first phase: its snapshots move the progress along it (no volume of the run in them, no
    # loss history), then the stages go on from there; the count never goes back
    pilot = [s for s in snaps if s.phase == PUPIL_PILOT]
    assert [s.plan_iteration for s in pilot] == list(range(10, PILOT_ITERATIONS + 1, 10))
    assert all(s.phase_name == "checking the pupil at Δn = 0, before the stages" and not s.delta_n.any() for s in pilot)
    counts = [s.plan_iteration for s in snaps]
    assert counts == sorted(counts) and counts[-1] == with_pilot.plan.iterations
    assert len(with_pilot.history) == len(without.history)


def test_a_resumed_run_keeps_the_early_trials(soft_pupil, tmp_path) -> None:
    """The pilot's trial (it kept nothing) is in the run's state: a run resumed from the first stage's checkpoint lists
    it first, as the run that went through does, and does not run the pilot again."""
    cfg = _config()
    whole = Reconstructor(soft_pupil, cfg, device="cpu")
    list(whole.run(checkpoint_dir=tmp_path))
    resumed = Reconstructor.from_checkpoint(tmp_path / "stage_0.pt", soft_pupil, device="cpu")
    assert resumed.early_trials is not None and resumed.early_trials.trials[0]["part"] == "pupil"
    snaps = list(resumed.run())
    assert not any(s.phase == PUPIL_PILOT for s in snaps)
    first, again = whole.parts_choice.trials[0], resumed.parts_choice.trials[0]
    assert again["pass"] == 0 and not again["on"]
    assert (again["part"], again["validation_error"]) == (first["part"], first["validation_error"])


def test_a_pupil_kept_before_the_stages_is_on_from_the_first(soft_pupil, monkeypatch) -> None:
    """The pilot's verdict forced to keep the pupil: it is on and fitted from the first stage, whose coarse stage runs
    the multi-slice model (the envelope model holds no pupil); no stage runs twice, the plan has no stages again, and
    the finest stage's end still chooses the other auto parts."""
    monkeypatch.setattr(parts_pilot, "decide", lambda ref, cand: {"on": True, "improvement": 1.0, "standard_error": 0.1,
                                                                  "threshold": 2.0})
    # (the backward step off: the forced pupil does not help, and at the end it would be dropped and the finest stage
    # run again; tests/test_parts_backward.py)
    rec, snaps = _run(soft_pupil, _config(obliquity_correction="auto", parts_backward=False))
    iterations = [s.global_iteration for s in snaps if s.phase != PUPIL_PILOT]
    choice = rec.parts_choice
    assert iterations == sorted(iterations) and iterations[-1] == sum(s.iterations for s in rec.config.stages)
    assert [s.plan_iteration for s in snaps] == sorted(s.plan_iteration for s in snaps)  # the bar never goes back
    assert choice.rerun == "before" and choice.parts["pupil"] and choice.chosen_by["pupil"] == "validation"
    assert choice.trials[0]["part"] == "pupil" and choice.trials[0]["pass"] == 0
    assert {t["part"] for t in choice.trials if t.get("pass") == 1} == {"obliquity"}  # chosen at the finest stage's end
    assert rec.coarse_model == "multislice" and not rec._build_stage(0).envelope
    assert rec.calibration.fit_pupil and all(s.model == "multislice" for s in rec.plan.phases)
    assert rec.plan.phases[0].pass_name == PUPIL_PILOT
    assert not any(p.pass_name == RERUN for p in rec.plan.phases)
    assert len(rec.stages) == len(rec.config.stages)
    assert "pupil (before the stages, at Δn = 0) on" in describe_parts(model_parts_summary(rec))


def test_no_pilot_where_the_pupil_is_stated_or_set(soft_pupil) -> None:
    stated = Reconstructor(soft_pupil, _config(calibrate_pupil="false"), device="cpu")
    assert not parts_pilot.pilot_due(stated)
    off = Reconstructor(soft_pupil, _config(parts_pilot=False), device="cpu")
    assert not parts_pilot.pilot_due(off)
    assert parts_pilot.pilot_due(Reconstructor(soft_pupil, _config(), device="cpu"))
