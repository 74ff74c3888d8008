"""The phases of a run (``Snapshot.phase``): the stages before the TV trials and the trials ("tv_choice"), the run, the
stages run again with kept parts. Whichever weight wins, an "auto" run ends as the run given it as a number."""

from __future__ import annotations

import io
import time
from types import SimpleNamespace

import numpy as np
import pytest

from napari_fdt.recon.choices import tv_search
from napari_fdt.recon.loop.model_parts import PARTS, PartsChoice
from napari_fdt.recon.loop.phases import TV_CHOICE, phase_label
from napari_fdt.recon.run.solver import Reconstructor, Snapshot
from napari_fdt.recon.settings.config import SolverConfig, StageConfig


def _config(**kw) -> SolverConfig:
    """Three stages: stage 0 runs at the smallest weight, the weights are tried at stage 1's start (the last coarse one)."""
    base = dict(stages=[StageConfig(4, 4), StageConfig(2, 6), StageConfig(1, 6)], batch_size=4, snapshot_every=2,
                validation_fraction=0.2, final_stage_min_passes=0)
    base.update(kw)
    return SolverConfig(**base)


def _forced(monkeypatch, k: int) -> None:
    """Make the trials pick the ``k``-th weight tried (the rule itself: test_regularisation.py)."""
    monkeypatch.setattr(tv_search, "pick", lambda trials: trials[min(k, len(trials) - 1)])


@pytest.mark.parametrize("winner", [0, 1], ids=["the smallest weight wins: the run goes on", "a larger weight wins: stage 0 again"])
def test_the_trials_report_their_progress_and_the_run_is_the_fixed_weights_run(scene16, monkeypatch, winner) -> None:
    acq = scene16.acquisition
    _forced(monkeypatch, winner)
    # (without the test of the aberrations at the last coarse stage's end, whose seconds are that stage's choice_s too:
    # tests/test_model_parts.py)
    auto = Reconstructor(acq, _config(parts_pilot=False), device="cpu")
    snaps = list(auto.run())
    choice = auto.tv_choice
    n = len(choice.trials)
    assert choice.stage == 1 and choice.probe_iterations == 2 and choice.tv_xy_weight == choice.trials[winner]["tv_xy_weight"]
    before, trials, run = snaps[:2], snaps[2:2 + n], snaps[2 + n:]
    assert [s.phase for s in before + trials] == [TV_CHOICE] * (2 + n) and {s.phase for s in run} == {"run"}
    assert [(s.stage, s.iteration, s.global_iteration, s.stage_complete) for s in before] == [(0, 2, 2, False), (0, 4, 4, True)]
    assert before[0].phase_name == "choosing the TV weight: stage 1/3 (x4) with the lightest TV" and before[0].tv_weights is None
    assert [s.tv_weights for s in trials] == [(t["tv_xy_weight"], t["tv_z_weight"]) for t in choice.trials]
    assert [s.validation_error for s in trials] == [t["validation_error"] for t in choice.trials]
    assert all((s.stage, s.iteration, s.global_iteration, s.stage_complete) == (1, 2, 6, False) for s in trials)
    assert [s.phase_iteration for s in trials] == [2 * (k + 1) for k in range(n)] and trials[-1].phase_iterations == 2 * n
    assert trials[0].phase_name == "choosing the TV weight at stage 2/3 (x2)"
    if winner == 0:  # the stages before ran with it: stage 1 goes on after the winner's 2 iterations
        assert [(s.stage, s.iteration) for s in run] == [(1, 4), (1, 6), (2, 2), (2, 4), (2, 6)]
        assert snaps[-1].plan_iterations == 4 + 2 * n + 4 + 6
        assert [r.stage for r in auto.stages] == [0, 1, 2] and 0 < auto.stages[1].choice_s < choice.seconds
    else:  # stage 0 again with the chosen weight, then every stage in full
        assert [(s.stage, s.iteration) for s in run] == [(0, 2), (0, 4), (1, 2), (1, 4), (1, 6), (2, 2), (2, 4), (2, 6)]
        assert snaps[-1].plan_iterations == 4 + 2 * n + 16
        assert [r.stage for r in auto.stages] == [0, 1, 2] and [r.choice_s == 0 for r in auto.stages] == [True, True, False]
    # the finest stage's choice of model parts is not its iterations' time (nor is the trials' that lost, above)
    assert abs(auto.stages[2].choice_s - auto.parts_choice.seconds) < 0.05 and auto.parts_choice.seconds < auto.stages[2].seconds
    done = [s.plan_iteration for s in snaps]
    assert done == sorted(done) and done[-1] == snaps[-1].plan_iterations  # one count, never back
    assert all(s.phase_label.startswith("choosing the smoothing (TV) weight") for s in before + trials)
    assert all(s.phase_label == "reconstructing" and s.tv_weights is None for s in run)
    elapsed = [s.elapsed_s for s in snaps]
    assert elapsed == sorted(elapsed)  # the choice's time is the run's
    assert all(s.eta_s > 0 for s in snaps[:-1]) and snaps[-1].eta_s == 0
    assert auto.last_complete is snaps[-1] and auto.completed_stages == 3
    # ... and the result is the run given the chosen weights as numbers, snapshot by snapshot from where they differ
    fixed = Reconstructor(acq, _config(tv_xy_weight=choice.tv_xy_weight, tv_z_weight=choice.tv_z_weight, parts_pilot=False),
                          device="cpu")
    fixed_snaps = list(fixed.run())
    tail = fixed_snaps[-len(run):]
    assert [(s.stage, s.iteration, s.global_iteration) for s in run] == [(s.stage, s.iteration, s.global_iteration) for s in tail]
    assert all(np.array_equal(a.delta_n, b.delta_n) and a.losses == b.losses for a, b in zip(run, tail))
    assert np.array_equal(auto.delta_n_full(), fixed.delta_n_full())
    assert np.array_equal(auto.sources_um(), fixed.sources_um())
    assert [r.validation_error for r in auto.stages] == [r.validation_error for r in fixed.stages]


def test_the_consumers_time_is_not_the_trials(scene16) -> None:
    rec = Reconstructor(scene16.acquisition, _config(), device="cpu")
    waited = 0.0
    t_start = time.perf_counter()
    for snap in rec.run():
        if snap.phase == TV_CHOICE:
            time.sleep(0.3)
            waited += 0.3
    wall = time.perf_counter() - t_start
    assert rec.tv_choice.seconds < waited
    assert rec.last_complete.elapsed_s <= wall - waited + 0.05  # the run's clock stopped while the consumer slept


def test_closing_during_the_trials_keeps_the_last_stage_and_a_new_run_chooses_again(scene16) -> None:
    """A consumer that stops iterating during the trials (closes the generator) keeps the last complete stage; the
    state is the selection stage's start; a new run tries the weights again and ends as an unbroken run."""
    acq = scene16.acquisition
    rec = Reconstructor(acq, _config(), device="cpu")
    gen = rec.run()
    for snap in gen:
        if snap.tv_weights is not None:
            break
    gen.close()
    assert rec.completed_stages == 1 and rec.last_complete.stage == 0 and rec.tv_choice is None
    assert (rec.loss_weights.tv_xy, rec.loss_weights.tv_z) == (1.0, 0.5)  # the weights the stages before the trials run with
    list(rec.run())
    unbroken = Reconstructor(acq, _config(), device="cpu")
    list(unbroken.run())
    untimed = lambda choice: [{k: v for k, v in t.items() if k != "seconds"} for t in choice.to_dict()["trials"]]  # noqa: E731
    assert untimed(rec.tv_choice) == untimed(unbroken.tv_choice)
    assert np.array_equal(rec.delta_n_full(), unbroken.delta_n_full())


def test_cancelling_in_the_trials_keeps_the_stage_before(scene16) -> None:
    rec = Reconstructor(scene16.acquisition, _config(), device="cpu")
    polls = iter(range(1000))
    snaps = list(rec.run(should_stop=lambda: next(polls) >= 7))  # 4 iterations of stage 0, then inside the trials
    assert all(s.phase == TV_CHOICE for s in snaps) and [s.tv_weights is None for s in snaps[:2]] == [True, True]
    assert rec.completed_stages == 1 and rec.tv_choice is None and rec.last_complete is snaps[1]


def test_cancelling_after_the_choice_keeps_the_stage_before(scene16, monkeypatch) -> None:
    """When stage 0 runs again with the chosen weight, a cancel in it still finds the last complete stage (stage 0
    of the choice) to return to."""
    _forced(monkeypatch, 1)
    rec = Reconstructor(scene16.acquisition, _config(), device="cpu")
    gen = rec.run()
    for snap in gen:
        if snap.phase == "run":
            break
    gen.close()
    assert rec.completed_stages == 0 and rec.last_complete.stage == 0 and rec.last_complete.phase == TV_CHOICE
    rec.restore_last_complete()
    assert rec.volume_factor == 4


def test_fixed_weights_have_no_trials_and_the_stages_run_again_are_a_rerun(scene16) -> None:
    acq = scene16.acquisition
    rec = Reconstructor(acq, _config(tv_xy_weight=0.0, tv_z_weight=0.0, stages=[StageConfig(2, 4), StageConfig(1, 4)]), device="cpu")
    assert {s.phase for s in rec.run()} == {"run"}
    # the stages run again with a kept part (as resumed from a checkpoint of the second pass): phase "rerun"
    rec = Reconstructor(acq, _config(tv_xy_weight=0.0, tv_z_weight=0.0, stages=[StageConfig(2, 4), StageConfig(1, 4)], parts_backward=False,
                                     calibrate_aberrations="auto", calibrate_pupil="false"), device="cpu")
    parts = {p: p == "aberrations" for p in PARTS}
    chosen_by = {p: ("validation" if p == "aberrations" else "setting") for p in PARTS}
    rec.apply_parts_choice(PartsChoice(parts, chosen_by, rerun="stages", pending=[]))
    snaps = [s for s in rec.run()]
    assert {s.phase for s in snaps} == {"rerun"} and {s.rerun_with for s in snaps} == {("aberrations",)}
    # the plan holds the first pass and the stages again; the count goes on after the first pass
    assert [p.pass_name for p in rec.plan.phases] == ["run", "run", "rerun", "rerun"]
    assert snaps[0].plan_iteration > 8 and snaps[-1].plan_iteration == snaps[-1].plan_iterations == 16
    assert snaps[0].phase_name == "stage 1/2 (x2) again with aberrations"
    assert snaps[0].phase_label == "reconstructing again with aberrations"


def test_labels() -> None:
    assert phase_label("run") == "reconstructing"
    assert phase_label("rerun", ("pixel_integration", "aberrations")) == "reconstructing again with pixel integration and aberrations"
    assert phase_label(TV_CHOICE) == "choosing the smoothing (TV) weight"
    assert phase_label(TV_CHOICE, tv_weights=(3.0, 1.5)) == "choosing the smoothing (TV) weight: tried xy 3, z 1.5"
    fields = Snapshot.__dataclass_fields__
    assert fields["phase"].default == "run" and fields["tv_weights"].default is None


class _Pipe(io.StringIO):
    def isatty(self) -> bool:
        return False


def _snap(done: int, of: int, name: str, *, weights=None, complete=False) -> SimpleNamespace:
    return SimpleNamespace(losses={"total": 1.0}, validation_error=0.1, eta_s=1.0, stage_complete=complete, tv_weights=weights,
                           plan_iteration=done, plan_iterations=of, phase_name=name)


def test_the_bar_counts_the_whole_plan_and_names_its_phase() -> None:
    from napari_fdt.cli import _progress_bar, _show_progress

    out = _Pipe()
    bar = _progress_bar(10, disable=False, stream=out)
    _show_progress(bar, _snap(2, 26, "stage 1/2 (x2)"))
    assert bar.n == 2 and bar.total == 26 and bar.desc.startswith("stage 1/2 (x2)")
    _show_progress(bar, _snap(4, 26, "stage 1/2 (x2)", complete=True))
    _show_progress(bar, _snap(6, 26, "choosing the TV weight at stage 2/2 (x1)", weights=(3.0, 1.5)))
    assert bar.n == 6 and "tried xy 3" in bar.desc
    _show_progress(bar, _snap(18, 22, "stage 2/2 (x1)"))  # the trials ended early: the plan's total shrank
    assert bar.n == 18 and bar.total == 22 and bar.desc.startswith("stage 2/2 (x1)") and "TV" not in bar.desc
    _show_progress(bar, _snap(24, 32, "stage 1/2 (x2) again with aberrations"))
    assert bar.n == 24 and bar.total == 32 and "again with aberrations" in bar.desc
    bar.close()
    text = out.getvalue()
    assert text.isascii() and "choosing the TV weight: tried xy 3, z 1.5: validation error 0.1000" in text
    assert "stage 1/2 (x2) complete" in text
    quiet = _progress_bar(10, disable=True, stream=_Pipe())
    for s in (_snap(2, 26, "x", weights=(1.0, 0.5)), _snap(3, 26, "y")):
        _show_progress(quiet, s)
    quiet.close()
