"""``field_oversampling = "before_spectral"`` (issue 49, physics before phenomenology): the 2x field grid is tried only
where the spectral model would be kept, and before it is. The verdicts are forced here (the mechanics are under test,
not the test's power: that is measured in docs/decisions/parts-backward.md)."""

from __future__ import annotations

import pytest

from tests.test_sub_slices import _auto_config, _letters_acquisition


def _verdicts(monkeypatch, on: dict[int, bool]) -> list[int]:
    """The parts' paired test with its verdict forced at its n-th call (1-based; off where not listed)."""
    import napari_fdt.recon.choices.parts_search as parts_search

    decide, calls = parts_search.decide, []

    def forced(ref, cand):
        calls.append(1)
        return {**decide(ref, cand), "on": on.get(len(calls), False)}

    monkeypatch.setattr(parts_search, "decide", forced)
    return calls


def _run(**settings):
    from napari_fdt.recon.run.solver import Reconstructor

    cfg = _auto_config(sub_slices=1, coherence="auto", field_oversampling="before_spectral", parts_branch=False, **settings)
    rec = Reconstructor(_letters_acquisition(1), cfg, device="cpu")
    list(rec.run())
    return rec


def test_the_grid_is_not_tried_where_the_spectral_model_is_rejected(monkeypatch) -> None:
    _verdicts(monkeypatch, {})
    rec = _run()
    assert [t["part"] for t in rec.parts_choice.trials] == ["spectral"]
    assert not rec.parts["spectral"] and not rec.parts["field_grid"]


def test_a_rejected_grid_leaves_the_spectral_model_as_it_was_tried(monkeypatch) -> None:
    """Spectral passes (call 1), the grid is tried from the reference before it and fails (call 2): the spectral model is
    kept with its own trial's errors as the reference, and the report says the grid was tried before keeping it."""
    from napari_fdt.recon.run.report import describe_parts, model_parts_summary

    _verdicts(monkeypatch, {1: True})
    rec = _run(parts_rerun="finest")
    trials = rec.parts_choice.trials
    assert [t["part"] for t in trials] == ["spectral", "field_grid"]
    assert trials[0]["on"] and "waits_for" not in trials[0]
    assert not trials[1]["on"] and trials[1]["before_part"] == "spectral"
    # the grid was judged against the errors before the spectral model, every held-out image paired
    n_held = len(rec.validation_indices)
    assert trials[1]["image_errors"][:n_held] != trials[0]["image_errors"][:n_held]
    assert rec.parts["spectral"] and not rec.parts["field_grid"]
    words = describe_parts(model_parts_summary(rec))
    assert "field_grid (tried before keeping the spectral model) off" in words


def test_a_kept_grid_sets_the_spectral_trial_aside_and_tries_it_again_through_the_grid(monkeypatch) -> None:
    """Spectral passes (call 1), the grid passes through the volume (call 2): the spectral model's first trial is set
    aside and it is tried again with the grid on (call 3, rejected): the grid alone is kept."""
    from napari_fdt.model.oversampled import OversampledModel
    from napari_fdt.recon.run.report import describe_parts, model_parts_summary

    _verdicts(monkeypatch, {1: True, 2: True})
    rec = _run(parts_rerun="finest")
    trials = rec.parts_choice.trials
    assert [t["part"] for t in trials][:3] == ["spectral", "field_grid", "spectral"]
    assert not trials[0]["on"] and trials[0]["waits_for"] == "field_grid"
    assert trials[1]["on"] and not trials[2]["on"]
    assert rec.parts["field_grid"] and not rec.parts["spectral"]
    assert isinstance(rec._build_stage(1).model, OversampledModel)
    assert "spectral (set aside: the 2x field grid tried first) off" in describe_parts(model_parts_summary(rec))


def test_the_plan_prices_the_grid_with_the_spectral_model_not_at_the_finest_stage() -> None:
    """The finest stage's test is priced as without the grid to choose, and what keeping the spectral model adds grows by
    the grid's test: the same seconds that ``"auto"`` adds to the finest stage's test."""
    from dataclasses import replace

    from napari_fdt.recon.loop.plan import plan_for

    acq = _letters_acquisition(1)
    base = _auto_config(sub_slices=1, coherence="auto", parts_rerun="stages")
    one, auto, lazy = (plan_for(acq, replace(base, field_oversampling=v), "cpu")[0] for v in (1, "auto", "before_spectral"))
    finest = [sum(ph.test_s for ph in p.phases) for p in (one, auto, lazy)]
    assert finest[2] == pytest.approx(finest[0]) and finest[1] > finest[0]
    assert lazy.if_spectral_kept_s - one.if_spectral_kept_s == pytest.approx(finest[1] - finest[0])
    # "if the data ask for sub-slices alone": the grid is not priced as a part of the finest stage on its own
    assert lazy.finest_parts == one.finest_parts and "field_grid" in auto.finest_parts
    assert "the 2x field grid tried first in its place" in lazy.summary() and "in its place" not in one.summary()


def test_a_family_member_that_shares_a_choice_of_no_parts_runs_the_camera_grid() -> None:
    """A member after a choice that kept nothing runs with every chosen part off, the grid's default included (else it
    would predict the test images again to choose nothing)."""
    from napari_fdt.recon.run.family import parts_off
    from napari_fdt.recon.settings.config import SolverConfig

    assert SolverConfig().field_oversampling == "before_spectral"
    off = parts_off(SolverConfig())
    assert off.field_oversampling == 1 and off.sub_slices == 1 and off.coherence == "none"
    assert parts_off(SolverConfig(field_oversampling=2)).field_oversampling == 2  # a number given is kept
