"""Optional model parts switched by the data ("auto"): the rule, the cached-exit pupil path, and the choice on scenes
with and without an aberration (issue 13 item 4)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from napari_fdt.cli import build_parser
from napari_fdt.errors import FDTInputError
from napari_fdt.recon.loop.model_parts import PARTS, PartsChoice, decide, requested_parts, standard_errors, switch
from napari_fdt.recon.run.solver import Reconstructor
from napari_fdt.recon.settings.config import SolverConfig, StageConfig


def test_settings_accept_auto_true_false() -> None:
    cfg = SolverConfig()
    assert (cfg.calibrate_pupil, cfg.calibrate_aberrations, cfg.obliquity_correction, cfg.coherence) == ("auto",) * 4
    assert requested_parts(cfg) == {p: None for p in PARTS}  # the 2x grid: "before_spectral", chosen by the data
    assert requested_parts(SolverConfig(field_oversampling=1))["field_grid"] is False
    fixed = SolverConfig(calibrate_pupil=True, calibrate_aberrations="false", obliquity_correction=False, coherence="spectral")
    assert requested_parts(fixed) == {"sub_slices": None, "field_grid": None,
                                     "pixel_integration": None, "obliquity": False, "spectral": True, "pupil": True, "aberrations": False}
    assert switch("auto") is None and switch("true") is True and switch(False) is False
    with pytest.raises(FDTInputError, match=r"^calibrate_pupil: "):
        SolverConfig(calibrate_pupil="maybe")
    args = build_parser().parse_args(["reconstruct", "ACQ", "--out", "x.tif", "--calibrate-aberrations", "true",
                                      "--obliquity-correction", "auto"])
    assert SolverConfig(calibrate_aberrations=args.calibrate_aberrations).calibrate_aberrations == "true"
    assert args.obliquity_correction == "auto"


def test_decide_is_a_paired_test_against_noise() -> None:
    ref = np.array([0.10, 0.20, 0.30, 0.40, 0.25])
    # every image better by 0.01 ± 0.001: far beyond t(0.975, 4) = 2.78 standard errors and 1 % of the reference
    better = ref - np.array([0.010, 0.011, 0.009, 0.010, 0.010])
    v = decide(ref, better)
    assert v["on"] and v["improvement"] == pytest.approx(0.01) and v["standard_error"] == pytest.approx(0.000316, rel=0.01)
    # the same mean improvement, but as noisy as it is large: mean 0.01, standard error 0.0089 (1.1 SE)
    noisy = ref - np.array([0.03, -0.01, 0.03, -0.01, 0.01])
    assert not decide(ref, noisy)["on"]
    # significant but below 1 % of the reference error (0.25): not worth a part
    tiny = ref - 0.002
    assert not decide(ref, tiny)["on"] and decide(ref, tiny, min_improvement=0.0)["on"]
    assert not decide(ref, ref + 0.01)["on"]  # worse
    # 2.5 standard errors: significant over 30 images (t = 2.05), not over 3 (t = 4.30, the SE itself is uncertain)
    for n, on in ((3, False), (30, True)):
        r = np.full(n, 0.3)
        d = 0.01 + 0.01 * np.resize([-1.0, 1.0, 0.0], n)  # mean 0.01 (+ rounding), known spread
        d = d - d.mean() + 2.5 * d.std(ddof=1) / np.sqrt(n)  # mean exactly 2.5 SE
        v = decide(r, r - d)
        assert v["improvement"] / v["standard_error"] == pytest.approx(2.5) and v["on"] is on
    assert standard_errors(3) == pytest.approx(4.303) and standard_errors(1000) == pytest.approx(1.96)
    assert not decide([0.2], [0.1])["on"]  # one image: no noise estimate, nothing switched on
    with pytest.raises(ValueError):
        decide(ref, ref[:3])


def test_next_pass_counts_the_passes_the_trials_were_made_in() -> None:
    from napari_fdt.recon.loop.model_parts import next_pass

    assert next_pass([{"pass": 0}]) == 1  # after the pilot: the first pass's finest stage
    assert next_pass([{"pass": 1}]) == 2  # after a first pass's finest stage (or its coarse stage's end)
    assert next_pass([{"pass": 1, "at_stage": 1}]) == 2
    # a coarse stage's trials in the second pass share its number with that pass's finest stage
    assert next_pass([{"pass": 1, "at_stage": 1}, {"pass": 2, "at_stage": 1}]) == 2
    assert next_pass([{"pass": 1}, {"pass": 2}]) == 3


def test_parts_choice_round_trips() -> None:
    c = PartsChoice({p: p == "aberrations" for p in PARTS}, {p: "validation" for p in PARTS}, stage=2, iteration=10,
                    reference_error=0.1, reference_image_errors=[0.1, 0.1], trials=[{"part": "aberrations", "on": True}],
                    fitted={"zernike_rad": {"spherical": 0.4}}, seconds=1.5, rerun="stages", pending=["pupil"])
    d = c.to_dict()
    assert d["needed"] == ["aberrations"]
    assert PartsChoice.from_dict(d).to_dict() == d


@pytest.mark.parametrize("integrate", [False, True])
def test_intensity_from_exit_equals_the_full_model(integrate: bool) -> None:
    """The pupil applied to the cached exit spectra gives the model's images for any NA, edge and Zernike phase."""
    from napari_fdt import Optics
    from napari_fdt.model.forward import MultiSliceModel
    from napari_fdt.physics.grid import plan_for_sources

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=3, slice_spacing_um=2.0, image_plane_um=0.0)
    src = torch.tensor([[0.5, -0.3, 12.0], [-1.0, 0.8, 14.0]], dtype=torch.float64)
    plan = plan_for_sources(o, (24, 24), src.numpy(), warn=False)
    m = MultiSliceModel(o, plan, device="cpu", dtype=torch.float64, pixel_integration=integrate)
    g = torch.Generator().manual_seed(0)
    dn = 0.02 * torch.rand((3, 24, 24), generator=g, dtype=torch.float64)
    exit_spec, spec0 = m.exit_spectra(dn, src)
    z = torch.tensor([0.3, 0.0, 0.1, 0.0, -0.2, 0.5], dtype=torch.float64)
    for over in ({}, {"na": 0.78, "pupil_edge": 0.05}, {"zernike": z}):
        full = m.intensity(dn, src, **over)
        cached = m.intensity_from_exit(exit_spec, spec0, src, **over)
        assert torch.allclose(full, cached, rtol=1e-10, atol=1e-12 * float(full.abs().max()))


@pytest.fixture(scope="module")
def scenes():
    """A 32×32, 3-slice letters scene (25 noisy images), simulated without and with 1.2 rad of primary spherical
    aberration (the solver is not told)."""
    from napari_fdt import Optics, simulate, source_grid
    from napari_fdt.sim.phantoms import text_phantom

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=3,
               slice_spacing_um=2.0, image_plane_um=0.0)
    dn = text_phantom((32, 32), 3, text="UC", delta_n=0.04)
    grid = source_grid(5, 8.0, 15.0)
    clean = simulate(dn, o, grid, seed=3, device="cpu", photons=5000.0)
    aberrated = simulate(dn, o, grid, seed=3, device="cpu", photons=5000.0, aberrations={"spherical": 1.2})
    return clean.acquisition, aberrated.acquisition


def _config(**kw) -> SolverConfig:
    base = dict(stages=[StageConfig(2, 10), StageConfig(1, 30)], batch_size=8, snapshot_every=5, validation_fraction=0.25,
                tv_xy_weight=0.0, tv_z_weight=0.0, pixel_integration="false", coherence="none", obliquity_correction="false",
                sub_slices=1, field_oversampling=1)
    base.update(kw)
    return SolverConfig(**base)


def _run(acq, cfg) -> Reconstructor:
    rec = Reconstructor(acq, cfg, device="cpu")
    for _ in rec.run():
        pass
    return rec


def test_auto_switches_the_aberrations_on_only_where_the_data_has_them(scenes) -> None:
    clean, aberrated = scenes
    rec = Reconstructor(aberrated, _config(obliquity_correction="auto"), device="cpu")
    run = list(rec.run())
    snaps = [(s_.global_iteration, s_.rerun_with, s_.stage) for s_ in run]
    choice = rec.parts_choice
    along = [s_.plan_iteration for s_ in run]  # the progress bar never goes back, and ends at the plan's total
    assert along == sorted(along) and along[-1] == rec.plan.iterations
    # the snapshots say when the stages run again and with what (the widget and the CLI show it: the count restarts)
    back = next(i for i, s_ in enumerate(snaps) if s_[1])
    assert back > 0 and snaps[back][0] <= snaps[back - 1][0]
    assert all(w == () for _, w, _ in snaps[:back]) and all(w == ("aberrations",) for _, w, _ in snaps[back:])
    assert choice is not None and choice.parts["aberrations"] and not choice.parts["obliquity"], choice.trials
    assert choice.chosen_by["aberrations"] == "validation" and choice.chosen_by["pixel_integration"] == "setting"
    assert choice.chosen_by["obliquity"] == "validation" and choice.chosen_by["pupil"] == "acquisition"
    # the right mode with the right sign: the fit with the volume held fixed finds part of it (the volume trained without
    # the part holds the rest), the stages trained again with the part on most of it (true 1.2 rad; defocus and the
    # sources' common depth offset share some of it)
    assert 0.15 < choice.fitted["zernike_rad"]["spherical"] < 1.2
    assert 0.5 < rec.calibration.summary()["aberration_spherical_rad"] < 1.5
    # the stages ran again with the part on: the held-out error is below the reference the choice started from
    assert rec.stages[-1].validation_error < choice.reference_error
    trial = next(t for t in choice.trials if t["part"] == "aberrations")
    assert trial["improvement"] > trial["threshold"] * trial["standard_error"]
    # found at the coarse stage's end (recon/choices/parts_coarse_end.py), through its volume on the finest model: every stage
    # ran again before the first pass's finest stage ran (no snapshot of it; the plan never held it twice)
    assert trial["at_stage"] == 0 and trial["pass"] == 1 and choice.stage == 0
    assert all(st == 0 for _, _, st in snaps[:back])
    assert [p.stage for p in rec.plan.phases] == [0, 0, 1]
    # parts_rerun "stages" (the default): the kept part made every stage run again, the coarse one multi-slice (the
    # envelope model holds no aberration), and the finest stage chose the parts not kept (pass 2)
    assert choice.rerun == "stages" and choice.pending == []
    assert rec.coarse_model == "multislice" and all(not s_.envelope for s_ in [rec._build_stage(0)])
    assert {t["pass"] for t in choice.trials} == {1, 2}
    assert {t["part"] for t in choice.trials if t["pass"] == 2} == {"obliquity"}  # the part not tested before, tried now
    assert len(rec.stages) == len(rec.config.stages)  # the records are the second pass's
    rec0 = _run(clean, _config(obliquity_correction="auto"))
    assert not any(rec0.parts_choice.parts.values()), rec0.parts_choice.trials
    assert rec0.parts_choice.rerun is None and rec0.coarse_model == "envelope"  # nothing kept: nothing runs again
    assert rec0.parts == {p: False for p in PARTS}
    # the coarse stage's test ran there too and its trial is listed first
    assert [(t["part"], t.get("at_stage")) for t in rec0.parts_choice.trials][:1] == [("aberrations", 0)]


def test_the_coarse_stages_test_keeping_nothing_leaves_the_run_as_it_was(scenes) -> None:
    """Where the test at the coarse stage's end keeps nothing, the run is the run without it (the volume, sources and
    pupil values set back; the test draws no random numbers)."""
    clean, _ = scenes
    cfg = _config(stages=[StageConfig(2, 10), StageConfig(1, 20)], final_stage_min_passes=0)
    with_test = _run(clean, cfg)
    assert any(t.get("at_stage") == 0 for t in with_test.parts_choice.trials)
    without = _run(clean, _config(stages=[StageConfig(2, 10), StageConfig(1, 20)], final_stage_min_passes=0, parts_pilot=False))
    assert not any("at_stage" in t for t in without.parts_choice.trials)
    assert np.array_equal(with_test.delta_n_full(), without.delta_n_full())
    assert np.array_equal(with_test.sources_um(), without.sources_um())


def test_a_second_pass_tries_the_pupil_at_its_coarse_stages_end() -> None:
    """A hard pupil and 1.2 rad of spherical aberration, neither stated: the aberrations are kept at the first pass's
    coarse stage's end; in the second pass (coarse stages multi-slice with them) the pupil is tried at the coarse
    stage's end, and is then either on from the finest stage's start (not tried again there) or tried again at the
    finest stage's end; the trials say which pass and where."""
    from napari_fdt import Optics, simulate, source_grid
    from napari_fdt.recon.run.report import describe_parts, model_parts_summary
    from napari_fdt.sim.phantoms import text_phantom

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=3,
               slice_spacing_um=2.0, image_plane_um=0.0)
    acq = simulate(text_phantom((32, 32), 3, text="UC", delta_n=0.04), o, source_grid(5, 8.0, 15.0), seed=3, device="cpu",
                   photons=5000.0, pupil_edge=0.0, aberrations={"spherical": 1.2}).acquisition
    acq.extra.pop("pupil_edge")
    rec = Reconstructor(acq, _config(), device="cpu")
    run = list(rec.run())
    choice = rec.parts_choice
    assert choice.parts["aberrations"] and choice.rerun == "stages", choice.trials
    where = [(t["part"], t["pass"], t.get("at_stage")) for t in choice.trials]
    assert where[0] == ("pupil", 0, None)  # the pilot at Δn = 0 (it misses this pupil)
    assert ("aberrations", 1, 0) in where and ("pupil", 2, 0) in where
    at_coarse = next(t for t in choice.trials if t["part"] == "pupil" and t.get("at_stage") == 0)
    at_finest = [t for t in choice.trials if t["part"] == "pupil" and t["pass"] == 2 and "at_stage" not in t]
    finest = [s_ for s_ in run if s_.stage == 1 and s_.phase == "rerun"]
    assert finest
    if at_coarse["on"]:  # the plan prices the finest stage with it
        assert rec.plan.phases[-1].parts == ("pupil", "aberrations")
        assert not at_finest and all("pupil" in s_.rerun_with for s_ in finest) and choice.parts["pupil"]
    else:
        assert len(at_finest) == 1 and all("pupil" not in s_.rerun_with for s_ in finest)
    assert "pupil (again, all stages rerun" in describe_parts(model_parts_summary(rec))


def test_parts_rerun_finest_runs_only_the_finest_stage_again(scenes) -> None:
    """The rule before ``parts_rerun`` "stages": the coarse stages run once, with the envelope model (CPU), and the finest
    stage again from its start with the kept part."""
    _, aberrated = scenes
    rec = _run(aberrated, _config(parts_rerun="finest"))
    choice = rec.parts_choice
    assert choice.parts["aberrations"] and choice.rerun is None and rec.coarse_model == "envelope"
    assert all("pass" not in t for t in choice.trials)
    assert rec.stages[-1].validation_error < choice.reference_error


def test_a_checkpoint_between_the_passes_resumes_the_second(scenes) -> None:
    """A choice read back mid-way through the second pass (a checkpoint of its coarse stages) restores what that pass
    runs with: the kept parts on, multi-slice coarse stages, the parts left to choose in the finest stage."""
    clean, _ = scenes
    rec = Reconstructor(clean, _config(), device="cpu")
    assert rec.coarse_model == "envelope"
    parts = {p: p == "aberrations" for p in PARTS}
    chosen_by = {p: ("validation" if p in ("aberrations", "pupil") else "setting") for p in PARTS}
    rec.apply_parts_choice(PartsChoice.from_dict(PartsChoice(parts, chosen_by, rerun="stages", pending=["pupil"]).to_dict()))
    assert rec.coarse_model == "multislice" and rec._choose_again == ["pupil"] and rec._auto_parts == ["pupil"]
    assert rec.calibration.fit_aberrations and not rec.calibration.fit_pupil
    assert rec.calibration.position_frozen_stages == frozenset()  # positions train in multi-slice coarse stages
    # ... with the multi-slice step length there (the stage roles follow the coarse model, as in an unbroken run)
    assert rec.calibration.envelope_stages == frozenset() and rec.calibration.depth_frozen_stages == frozenset()


def test_no_choice_without_a_split_or_with_fixed_settings(scenes) -> None:
    clean, _ = scenes
    rec = Reconstructor(clean, _config(validation_fraction=0.0), device="cpu")
    assert rec.parts_choice is not None and rec.parts_choice.chosen_by["aberrations"] == "no validation split"
    assert not rec.parts["aberrations"] and not rec.parts["pupil"]
    fixed = Reconstructor(clean, _config(calibrate_pupil="false", calibrate_aberrations="true"), device="cpu")
    assert fixed.parts_choice is not None and fixed.parts["aberrations"] and fixed.calibration.fit_aberrations


def test_describe_parts_names_the_second_pass() -> None:
    from napari_fdt.recon.run.report import describe_parts

    chosen = {"reference_error": 0.2, "stage": 2, "seconds": 3.0, "trials": [
        {"part": "aberrations", "on": True, "improvement": 0.02, "pass": 1},
        {"part": "pupil", "on": True, "improvement": 0.004, "pass": 2}]}
    line = describe_parts({"needed": ["pupil", "aberrations"], "chosen": chosen})
    # improvements relative to the first reference: 0.02 / 0.2 = 10 %, 0.004 / 0.2 = 2 %
    assert "aberrations on (-10.0 %)" in line and "pupil (again, all stages rerun) on (-2.0 %)" in line
    # a part found at a coarse stage's end (recon/choices/parts_coarse_end.py), each trial against its own reference
    chosen = {"reference_error": 0.2, "stage": 1, "seconds": 3.0, "trials": [
        {"part": "aberrations", "on": True, "improvement": 0.01, "pass": 1, "at_stage": 1, "reference_error": 0.25},
        {"part": "obliquity", "on": False, "improvement": -0.002, "pass": 2, "after": "stages"}]}
    line = describe_parts({"needed": ["aberrations"], "chosen": chosen})
    assert "in stage 2" in line and "aberrations (at stage 2's end) on (-4.0 %)" in line
    assert "obliquity (again, all stages rerun) off (+1.0 %)" in line


def test_parts_test_images_adds_the_training_images_not_fitted(scenes) -> None:
    """``held_out+training``: the paired test's images are the held-out ones, then every training image outside the
    pupil fit's subset, each with its relative error ‖g·p − m‖/‖m‖ at the least-squares gain g = ⟨p, m⟩/⟨p, p⟩."""
    import dataclasses

    clean, _ = scenes
    rec = _run(clean, _config(calibrate_pupil="false", calibrate_aberrations="false", parts_test_images="held_out"))
    stage = rec._build_stage(len(rec.config.stages) - 1)
    mask = rec._loss_mask(stage)
    err, held = rec._choice_errors(stage, mask)
    assert err == rec.validation_error(stage, mask) and len(held) == len(rec.validation_indices)
    rec.config = dataclasses.replace(rec.config, parts_test_images="held_out+training")
    err2, both = rec._choice_errors(stage, mask)
    train = np.setdiff1d(np.setdiff1d(np.arange(clean.n_images), rec.validation_indices), rec._fit_images().numpy())
    assert err2 == err and both[: len(held)] == held and len(both) == len(held) + len(train) and len(train) > len(held)
    pred = rec.predict(train, stage).astype(np.float64)
    meas = (stage.images[torch.as_tensor(train)].numpy() * rec.image_scale).astype(np.float64)
    g = (pred * meas).sum(axis=(1, 2)) / (pred * pred).sum(axis=(1, 2))
    ref = np.sqrt(((g[:, None, None] * pred - meas) ** 2).sum(axis=(1, 2)) / (meas**2).sum(axis=(1, 2)))
    np.testing.assert_allclose(both[len(held):], ref, rtol=1e-4)


def test_the_choice_on_more_images_still_keeps_only_what_the_data_has(scenes) -> None:
    """With ``held_out+training`` the whole choice runs on the larger test set: the aberration is kept where the data has
    it, nothing on the clean scene (the paired test's false positives do not grow with the images)."""
    clean, aberrated = scenes
    cfg = _config(obliquity_correction="auto", parts_test_images="held_out+training")
    rec = _run(aberrated, cfg)
    assert rec.parts_choice.parts["aberrations"] and not rec.parts_choice.parts["obliquity"], rec.parts_choice.trials
    n_test = len(rec.parts_choice.trials[0]["image_errors"])
    assert n_test > len(rec.validation_indices)
    rec0 = _run(clean, cfg)
    assert not any(rec0.parts_choice.parts.values()), rec0.parts_choice.trials


def test_the_reports_predictions_use_the_model_the_run_fitted(scene16) -> None:
    """The image fit of RI.json and the widget's predicted-vs-measured (Reconstructor.evaluation_stage) use the run's
    camera, pupil edge and sub-slices: the same images as the finest stage's own model (they used point samples and
    the default pupil before)."""
    from napari_fdt.recon.run.solver import Reconstructor
    from napari_fdt.recon.settings.config import SolverConfig, StageConfig

    cfg = SolverConfig(stages=[StageConfig(1, 2)], batch_size=4, final_stage_min_passes=0, tv_xy_weight=0.0, tv_z_weight=0.0,
                       pixel_integration=True, pupil_edge=0.0, sub_slices=2, calibrate_pupil=False,
                       calibrate_aberrations=False, obliquity_correction=False, coherence="none")
    rec = Reconstructor(scene16.acquisition, cfg, device="cpu")
    list(rec.run())
    model = rec.evaluation_stage().model
    assert model.pixel_integration and model.pupil_edge == 0.0 and model.sub_slices == 2
    idx = [0, 5, 9]
    assert np.allclose(rec.predict(idx), rec.predict(idx, stage=rec._build_stage(0)), rtol=1e-5, atol=1e-7)


def test_a_real_cameras_pixel_integration_follows_the_physical_rule() -> None:
    """Files that do not state pixel integration (a microscope's, not ``fdt simulate``'s): every camera integrates over
    its pixels, so the physical rule sets it from the first stage (on where the intensity's band 2·NA/λ exceeds the
    camera's Nyquist 1/(2·dx)); it is not a choice of the data, which missed it on cells_pupil's images (the finest
    stage's test, through a volume trained without it, found it +3.5 % and +8.0 % worse; the whole runs with it ended
    at Δn error 0.258 and 0.101 against 0.305 and 0.163, docs/decisions/model-parts.md). A statement, or a simulated
    folder without one, is taken as it is."""
    from napari_fdt import Acquisition, Optics
    from napari_fdt.recon.loop.model_parts import requested_for

    def requested(na: float, extra: dict) -> tuple[bool | None, str]:
        o = Optics(wavelength_um=0.635, n_background=1.33, na=na, pixel_size_um=0.33, n_slices=4, slice_spacing_um=2.0)
        acq = Acquisition(np.ones((2, 16, 16), np.float32), o, None, extra=extra)
        req, why = requested_for(SolverConfig(), acq)
        return req["pixel_integration"], why["pixel_integration"]

    on, why = requested(0.8, {})  # 2·0.8/0.635 = 2.52 /µm > 1/(2·0.33) = 1.52 /µm
    assert on is True and why.startswith("physics: ")
    off, why = requested(0.3, {})  # 0.94 < 1.52
    assert off is False and why.startswith("physics: ")
    assert requested(0.8, {"pixel_integration": False}) == (False, "acquisition")
    assert requested(0.8, {"simulated": {}}) == (False, "acquisition")  # written before the camera model: point samples


def test_a_schedule_that_ends_coarse_on_the_envelope_model_tests_no_part(scene16) -> None:
    """The finest stage at x2 on the envelope model (the CPU's coarse model) holds none of the parts: every "auto" part
    is off, with the reason, and the run ends; before, the aberrations' test at the x4 stage's end went through that
    model's missing exit spectra and the run died after its stages (AttributeError). The multi-slice coarse model
    still tests them at x2 (the plan says so too)."""
    from napari_fdt.recon.loop.plan import plan_for

    cfg = SolverConfig(stages=[StageConfig(4, 10), StageConfig(2, 10)], tv_xy_weight=1.0, tv_z_weight=0.5,
                       final_stage_min_passes=0, coarse_model="envelope")
    rec = Reconstructor(scene16.acquisition, cfg, device="cpu")
    assert rec._auto_parts == [] and rec.parts_choice is not None
    assert all(not on for on in rec.parts.values() if on is not None)
    why = rec.parts_choice.chosen_by
    assert "envelope model" in why["aberrations"] and "envelope model" in why["sub_slices"]
    snaps = list(rec.run())
    assert snaps[-1].stage == 1 and np.isfinite(rec.delta_n_full()).all()
    plan, _ = plan_for(scene16.acquisition, cfg, "cpu")
    assert not any(p.test_s for p in plan.phases)
    multi, _ = plan_for(scene16.acquisition, SolverConfig(stages=cfg.stages, coarse_model="multislice"), "cpu")
    assert any(p.test_s for p in multi.phases)
