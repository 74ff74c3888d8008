"""The phases of a run (``Snapshot.phase``): the pilot that chooses the TV weight reports its progress, the pass follows,
and what the pass computes is what it computed when the pilot yielded nothing."""

from __future__ import annotations

import io
import time
from types import SimpleNamespace

import numpy as np

from napari_fdt.recon.config import SolverConfig, StageConfig
from napari_fdt.recon.model_parts import PARTS, PartsChoice
from napari_fdt.recon.phases import TV_CHOICE, phase_label, pilot_plan
from napari_fdt.recon.regularisation import TV_PATH
from napari_fdt.recon.solver import Reconstructor, Snapshot


def _config(**kw) -> SolverConfig:
    """Three stages: the pilot runs stage 0, then tries the weights at stage 1 (the last coarse one)."""
    base = dict(stages=[StageConfig(4, 4), StageConfig(2, 6), StageConfig(1, 6)], batch_size=4, snapshot_every=2,
                validation_fraction=0.2, final_stage_min_passes=0)
    base.update(kw)
    return SolverConfig(**base)


def test_the_pilot_reports_its_progress_and_the_pass_is_unchanged(scene16) -> None:
    acq = scene16.acquisition
    auto = Reconstructor(acq, _config(), device="cpu")
    snaps = list(auto.run())
    phases = [s.phase for s in snaps]
    first = phases.index("run")
    assert first > 0 and set(phases[:first]) == {TV_CHOICE} and set(phases[first:]) == {"run"}  # never back to the pilot
    pilot, run = snaps[:first], snaps[first:]
    plan = pilot_plan(auto.config)
    assert (plan.stage, plan.before, plan.probe, plan.n_trials) == (1, 4, 2, len(TV_PATH))
    # the pilot's stage 0 (as the pass numbers it), then one snapshot per weight tried, the trial's weights and error
    stage0, trials = pilot[: -len(TV_PATH)], pilot[-len(TV_PATH):]
    assert [(s.stage, s.iteration, s.global_iteration, s.stage_complete) for s in stage0] == [(0, 2, 2, False), (0, 4, 4, True)]
    assert all(s.tv_weights is None for s in stage0)
    choice = auto.tv_choice
    assert [s.tv_weights for s in trials] == [(t["tv_xy_weight"], t["tv_z_weight"]) for t in choice.trials]
    assert [s.validation_error for s in trials] == [t["validation_error"] for t in choice.trials]
    assert all((s.stage, s.iteration, s.global_iteration, s.stage_complete) == (1, 2, 6, False) for s in trials)
    # the pilot's own count: its stages', then each trial's iterations, up to its total
    assert [s.phase_iteration for s in pilot] == [2, 4] + [4 + 2 * (k + 1) for k in range(len(TV_PATH))]
    assert all(s.phase_iterations == plan.iterations == 16 for s in pilot) and pilot[-1].phase_progress == 1.0
    assert all(s.phase_label.startswith("choosing the smoothing (TV) weight") for s in pilot)
    assert trials[2].phase_label == f"choosing the smoothing (TV) weight: tried xy {TV_PATH[2]:g}, z {TV_PATH[2] / 2:g}"
    assert all(0 <= s.global_iteration <= s.total_iterations for s in snaps)
    elapsed = [s.elapsed_s for s in snaps]
    assert elapsed == sorted(elapsed)  # the pilot's time is the run's
    assert run[0].elapsed_s >= choice.seconds > 0
    # the time left covers the rest of the pilot and then the whole pass
    assert all(s.eta_s > 0 for s in pilot) and run[-1].eta_s == 0
    assert all(s.phase_label == "reconstructing" and s.tv_weights is None for s in run)
    assert all((s.phase_iteration, s.phase_iterations) == (s.global_iteration, s.total_iterations) for s in run)
    # the bookkeeping is the pass's alone
    assert auto.last_complete is run[-1] and auto.completed_stages == 3
    assert len(auto.history) == len(run) and [r.stage for r in auto.stages] == [0, 1, 2]
    # ... and so is the result: the pass equals a run given the chosen weights as numbers, snapshot by snapshot
    fixed = Reconstructor(acq, _config(tv_xy_weight=choice.tv_xy_weight, tv_z_weight=choice.tv_z_weight), device="cpu")
    fixed_snaps = list(fixed.run())
    assert [(s.stage, s.iteration, s.global_iteration, s.phase) for s in run] == \
           [(s.stage, s.iteration, s.global_iteration, s.phase) for s in fixed_snaps]
    assert all(np.array_equal(a.delta_n, b.delta_n) and a.losses == b.losses for a, b in zip(run, fixed_snaps))
    assert np.array_equal(auto.delta_n_full(), fixed.delta_n_full())
    assert np.array_equal(auto.sources_um(), fixed.sources_um())
    assert [r.validation_error for r in auto.stages] == [r.validation_error for r in fixed.stages]


def test_the_consumers_time_is_not_the_pilots(scene16) -> None:
    rec = Reconstructor(scene16.acquisition, _config(), device="cpu")
    waited = 0.0
    for snap in rec.run():
        if snap.phase == TV_CHOICE:
            time.sleep(0.3)
            waited += 0.3
    assert rec.tv_choice.seconds < waited


def test_closing_during_the_pilot_leaves_nothing_of_it(scene16) -> None:
    """A consumer that stops iterating in the pilot (closes the generator) finds the initial state: no stage complete
    (the pilot's stage is not a result), no choice; a new run chooses again and ends as an unbroken one."""
    acq = scene16.acquisition
    rec = Reconstructor(acq, _config(), device="cpu")
    gen = rec.run()
    for snap in gen:
        if snap.stage_complete:
            assert snap.phase == TV_CHOICE and rec.completed_stages == 1  # the pilot's stage 0
            break
    gen.close()
    assert rec.completed_stages == 0 and rec.last_complete is None and rec.volume is None and rec.tv_choice is None
    assert rec.history == [] and rec.stages == []
    list(rec.run())
    unbroken = Reconstructor(acq, _config(), device="cpu")
    list(unbroken.run())
    untimed = lambda choice: [{k: v for k, v in t.items() if k != "seconds"} for t in choice.to_dict()["trials"]]  # noqa: E731
    assert untimed(rec.tv_choice) == untimed(unbroken.tv_choice)
    assert np.array_equal(rec.delta_n_full(), unbroken.delta_n_full())


def test_cancelling_in_the_trials_yields_only_the_pilots_snapshots(scene16) -> None:
    rec = Reconstructor(scene16.acquisition, _config(), device="cpu")
    polls = iter(range(1000))
    snaps = list(rec.run(should_stop=lambda: next(polls) >= 7))  # 4 iterations of stage 0, then inside the trials
    assert snaps and all(s.phase == TV_CHOICE for s in snaps)
    assert rec.completed_stages == 0 and rec.tv_choice is None and rec.volume is None


def test_fixed_weights_have_no_pilot_and_the_stages_run_again_are_a_rerun(scene16) -> None:
    acq = scene16.acquisition
    rec = Reconstructor(acq, _config(tv_xy_weight=0.0, tv_z_weight=0.0, stages=[StageConfig(2, 4), StageConfig(1, 4)]), device="cpu")
    assert {s.phase for s in rec.run()} == {"run"}
    # the stages run again with a kept part (as resumed from a checkpoint of the second pass): phase "rerun"
    rec = Reconstructor(acq, _config(tv_xy_weight=0.0, tv_z_weight=0.0, stages=[StageConfig(2, 4), StageConfig(1, 4)],
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
    _show_progress(bar, _snap(2, 26, "choosing the TV weight: stage 1/2 (x2)"))
    assert bar.n == 2 and bar.total == 26 and bar.desc.startswith("choosing the TV weight: stage 1/2 (x2)")
    _show_progress(bar, _snap(4, 26, "choosing the TV weight: stage 1/2 (x2)", complete=True))
    _show_progress(bar, _snap(6, 26, "choosing the TV weight: trials at stage 2/2 (x1)", weights=(3.0, 1.5)))
    assert bar.n == 6 and "tried xy 3" in bar.desc
    _show_progress(bar, _snap(18, 22, "stage 1/2 (x2)"))  # the trials ended early: the plan's total shrank
    assert bar.n == 18 and bar.total == 22 and bar.desc.startswith("stage 1/2 (x2)") and "TV" not in bar.desc
    _show_progress(bar, _snap(24, 32, "stage 1/2 (x2) again with aberrations"))
    assert bar.n == 24 and bar.total == 32 and "again with aberrations" in bar.desc
    bar.close()
    text = out.getvalue()
    assert text.isascii() and "choosing the TV weight: tried xy 3, z 1.5: validation error 0.1000" in text
    assert "choosing the TV weight: stage 1/2 (x2) complete" in text
    quiet = _progress_bar(10, disable=True, stream=_Pipe())
    for s in (_snap(2, 26, "x", weights=(1.0, 0.5)), _snap(3, 26, "y")):
        _show_progress(quiet, s)
    quiet.close()
