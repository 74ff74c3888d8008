"""The backward step of the "auto" model parts (issue 49): a kept part earns its place in the final state, or is
dropped and the finest stage runs again without it (recon/choices/parts_backward.py)."""

from __future__ import annotations

import numpy as np
import pytest

from napari_fdt.recon.choices.parts_backward import keep_the_better
from napari_fdt.recon.loop.model_parts import PARTS, PartsChoice, decide
from napari_fdt.recon.run.solver import Reconstructor
from napari_fdt.recon.settings.config import SolverConfig, StageConfig


def _acquisition(**effects):
    """The 32×32, 3-slice letters scene of tests/test_model_parts.py (25 noisy images), with ``effects`` passed to the
    simulator (none: no aberration, no emission band)."""
    from napari_fdt import Optics, simulate, source_grid
    from napari_fdt.sim.phantoms import text_phantom

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=3,
               slice_spacing_um=2.0, image_plane_um=0.0)
    dn = text_phantom((32, 32), 3, text="UC", delta_n=0.04)
    return simulate(dn, o, source_grid(5, 8.0, 15.0), seed=3, device="cpu", photons=5000.0, **effects).acquisition


def _config(**kw) -> SolverConfig:
    base = dict(stages=[StageConfig(2, 10), StageConfig(1, 30)], batch_size=8, snapshot_every=5, validation_fraction=0.25,
                tv_xy_weight=0.0, tv_z_weight=0.0, pixel_integration="false", coherence="none", obliquity_correction="false",
                sub_slices=1, field_oversampling=1, calibrate_pupil="false")
    base.update(kw)
    return SolverConfig(**base)


def _run(acq, cfg) -> tuple[Reconstructor, list]:
    rec = Reconstructor(acq, cfg, device="cpu")
    return rec, list(rec.run())


def test_a_part_the_data_have_earns_its_place_in_the_final_state() -> None:
    """1.2 rad of primary spherical aberration the solver is not told: the aberrations are kept, and in the final state
    taking them out makes the held-out images worse by more than the admission's threshold; nothing runs again."""
    rec, _ = _run(_acquisition(aberrations={"spherical": 1.2}), _config())
    back = rec.parts_choice.backward
    assert rec.parts["aberrations"] and back is not None, rec.parts_choice.trials
    (effect,) = back["effects"]
    assert effect["part"] == "aberrations" and effect["earns"] and back["dropped"] == [] and back["rerun"] is None
    assert effect["improvement"] > effect["threshold"] * effect["standard_error"]
    assert effect["improvement"] > 0.01 * back["reference_error"]
    # the final state's held-out error is the run's own last validation error (the same images, the same model)
    assert back["reference_error"] == pytest.approx(rec.stages[-1].validation_error, rel=1e-5)
    assert effect["validation_error_without"] > back["reference_error"]


def test_a_part_kept_by_a_false_admission_is_dropped_and_the_finest_stage_runs_again(monkeypatch) -> None:
    """A scene without an emission band, whose spectral model is admitted whatever the held-out images say (the
    admission forced on, as noise could): every stage runs again with it; at the end its removal is not worse by more
    than noise, so it is dropped, the finest stage runs again from its start without it (priced in the plan, its
    snapshots say so), and that rerun is kept: its held-out images are no worse than with the part."""
    import napari_fdt.recon.choices.parts_search as parts_search

    def admit(reference, candidate, **kw):
        return {**decide(reference, candidate, **kw), "on": True}

    monkeypatch.setattr(parts_search, "decide", admit)
    rec, snaps = _run(_acquisition(), _config(coherence="auto", calibrate_aberrations="false"))
    choice = rec.parts_choice
    assert choice.rerun == "stages" and any(t["part"] == "spectral" and t["on"] for t in choice.trials)
    back = choice.backward
    (effect,) = back["effects"]
    assert effect["part"] == "spectral" and not effect["earns"] and back["dropped"] == ["spectral"]
    assert not (effect["improvement"] > effect["threshold"] * effect["standard_error"]
                and effect["improvement"] > 0.01 * back["reference_error"])
    # dropped: the model is the one without it, and the result is the finest stage trained again without it
    assert not rec.parts["spectral"] and not choice.parts["spectral"] and rec.wavelengths is None
    assert back["rerun"]["keep_rerun"]
    assert back["rerun"]["validation_error_rerun"] == pytest.approx(rec.stages[-1].validation_error, rel=1e-5)
    last = rec.plan.phases[-1]
    assert last.stage == 1 and last.pass_name == "rerun" and "spectral" not in last.parts
    finest = [s.plan_iteration for s in snaps]
    assert finest == sorted(finest) and finest[-1] == rec.plan.iterations  # the bar never goes back
    assert rec.plan.if_part_dropped_s is None  # the step is made: nothing more to price for it
    from napari_fdt.recon.run.report import describe_parts, model_parts_summary

    words = describe_parts(model_parts_summary(rec))
    assert "spectral dropped" in words and "ran again without the dropped parts and was kept" in words


def test_parts_backward_off_leaves_the_kept_parts(monkeypatch) -> None:
    import napari_fdt.recon.choices.parts_search as parts_search

    monkeypatch.setattr(parts_search, "decide", lambda r, c, **kw: {**decide(r, c, **kw), "on": True})
    rec, _ = _run(_acquisition(), _config(coherence="auto", calibrate_aberrations="false", parts_backward=False))
    assert rec.parts["spectral"] and rec.parts_choice.backward is None


def test_the_rerun_is_kept_unless_worse_by_more_than_noise() -> None:
    before = np.array([0.10, 0.20, 0.30, 0.40, 0.25])
    assert keep_the_better(list(before), list(before - 0.01), 0.24)["keep_rerun"]  # better
    assert keep_the_better(list(before), list(before + np.array([0.01, -0.01, 0.01, -0.01, 0.0])), 0.25)["keep_rerun"]  # noise
    worse = keep_the_better(list(before), list(before + 0.01), 0.26)  # every image worse by 0.01 ± 0: far beyond noise
    assert not worse["keep_rerun"] and worse["improvement_before_drop"] == pytest.approx(0.01)


def test_the_plan_prices_a_drop_and_the_choice_round_trips() -> None:
    from napari_fdt.recon.loop.plan import plan_for

    acq = _acquisition()
    plan, _ = plan_for(acq, _config(calibrate_aberrations="auto"), "cpu")
    finest = plan.phases[-1]  # its iterations again (the tests at its end do not run again)
    assert plan.if_part_dropped_s == pytest.approx(finest.iterations * finest.seconds_per_iteration)
    assert "if a kept part no longer helps at the end" in plan.summary()
    assert plan_for(acq, _config(calibrate_aberrations="auto", parts_backward=False), "cpu")[0].if_part_dropped_s is None
    c = PartsChoice({p: False for p in PARTS}, {p: "validation" for p in PARTS},
                    backward={"reference_error": 0.1, "effects": [], "dropped": [], "rerun": None})
    assert PartsChoice.from_dict(c.to_dict()).to_dict() == c.to_dict()
