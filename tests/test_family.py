"""A family of volumes across TV weights (issue 47, first part): each member is the whole run at its weight, the verdict
compares the members' held-out images pair by pair, and ``fdt reconstruct --tv-family`` writes every member and the pick."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from napari_fdt.cli import main
from napari_fdt.cli.family import member_path
from napari_fdt.data.io import read_volume_tiff, write_acquisition
from napari_fdt.recon.run.family import FAMILY_TAUS, Member, member_config, verdict
from napari_fdt.recon.settings.config import SolverConfig, StageConfig


def _member(tau: float, errors: list[float]) -> Member:
    m = Member(tau, tau, tau / 2)
    m.image_errors = list(errors)
    m.validation_error = float(np.sqrt(np.mean(np.square(errors))))  # any number ordered like the errors serves here
    return m


def test_the_verdict_is_paired_and_the_pick_the_largest_weight_within_the_tolerance() -> None:
    best = [0.10, 0.20, 0.30, 0.40]
    close = [0.102, 0.203, 0.301, 0.404]     # +1 % everywhere: within 5 %, and told apart (a consistent rise)
    noisy = [0.09, 0.22, 0.29, 0.43]         # the same mean rise, but scattered: the images cannot tell it apart
    far = [0.12, 0.24, 0.36, 0.48]           # +20 %
    members = [_member(1.0, best), _member(3.0, noisy), _member(10.0, far)]
    pick, reason = verdict(members)
    assert pick == 1 and "5%" in reason  # within 5 % and not told apart: the larger weight
    members = [_member(1.0, best), _member(3.0, close), _member(10.0, far)]
    pick, reason = verdict(members)
    # within 5 %, but the images tell it apart (every image worse): the data speak, the best member is the pick
    assert pick == 0 and "cannot tell" in reason
    d = np.array(close) - np.array(best)
    assert members[1].mean_difference == pytest.approx(d.mean())
    assert members[1].standard_error == pytest.approx(d.std(ddof=1) / 2)
    assert members[0].indistinguishable and not members[1].indistinguishable and not members[2].indistinguishable
    members = [_member(1.0, best), _member(3.0, noisy)]
    verdict(members)
    assert members[1].indistinguishable
    lone = [Member(1.0, 1.0, 0.5), Member(3.0, 3.0, 1.5)]  # no held-out images: the smallest weight, no verdict
    assert verdict(lone)[0] == 0 and lone[1].mean_difference is None


def test_member_configs_and_paths() -> None:
    cfg = member_config(SolverConfig(tv_family=True), 3.0)
    assert (cfg.tv_xy_weight, cfg.tv_z_weight, cfg.tv_family) == (3.0, 1.5, "false")
    assert member_path(Path("/x/RI.tif"), 3.0) == Path("/x/RI_tv3.tif")
    assert member_path(Path("/x/RI.ome.tif"), 10.0) == Path("/x/RI_tv10.ome.tif")
    assert member_path(Path("/x/RI.ome.zarr"), 1.0) == Path("/x/RI_tv1.ome.zarr")


@pytest.mark.parametrize("extra,field", [(["--tv-xy-weight", "3"], "tv_family"), (["--half-set-resolution"], "tv_family"),
                                         (["--resume", "ck"], "tv_family")])  # ck: not a family's checkpoint folder
def test_what_a_family_cannot_do_is_refused_before_the_run(tmp_path: Path, tiny_sim, capsys, extra, field) -> None:
    acq = write_acquisition(tiny_sim.acquisition, tmp_path / "acq")
    code = main(["reconstruct", str(acq), "--out", str(tmp_path / "RI.tif"), "--tv-family", "--device", "cpu", *extra])
    assert code == 2 and f"error: {field}:" in capsys.readouterr().err
    assert not list(tmp_path.glob("RI*"))


def test_auto_makes_a_family_on_cuda_unless_the_command_excludes_one(monkeypatch) -> None:
    """``tv_family`` "auto": a family on a CUDA device (docs/decisions/tv-family.md, "Default, per device"), one run on
    the CPU, and one run wherever the command asks for what a family cannot do (then nothing is refused)."""
    import argparse

    import torch

    from napari_fdt.cli import build_parser
    from napari_fdt.cli.family import family_on

    def args(*extra: str) -> tuple[SolverConfig, argparse.Namespace]:
        ns = build_parser().parse_args(["reconstruct", "ACQ", "--out", "RI.tif", *extra])
        from napari_fdt.cli import _config_from_args

        return _config_from_args(ns), ns

    assert SolverConfig().tv_family == "auto"
    assert not family_on(*args("--device", "cpu"))
    assert family_on(*args("--device", "cpu", "--tv-family"))  # asked for: on any device
    assert args("--tv-family", "false")[0].tv_family == "false"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert family_on(*args("--device", "cuda")) and family_on(*args())  # "auto" device: CUDA here
    assert not family_on(*args("--device", "cuda", "--tv-family", "false"))
    for extra in (["--tv-xy-weight", "3"], ["--resume", "ck"], ["--half-set-resolution"], ["--error-bounds"]):
        assert not family_on(*args("--device", "cuda", *extra)), extra
    assert family_on(*args("--device", "cuda", "--checkpoint-dir", "ck"))  # each member writes its own checkpoints
    assert not family_on(*args("--device", "cuda"), distributed_launch=True)  # a launch sized for one run
    assert family_on(*args("--device", "cuda", "--tv-family"), distributed_launch=True)  # asked for: run distributed


def _short() -> SolverConfig:
    return SolverConfig(stages=[StageConfig(2, 6), StageConfig(1, 8)], batch_size=4, final_stage_min_passes=0)


def test_a_family_writes_each_member_as_the_run_at_its_weight_and_the_pick(tmp_path: Path, scene16, capsys) -> None:
    acq = write_acquisition(scene16.acquisition, tmp_path / "acq")
    _short().save(tmp_path / "cfg.json")
    out = tmp_path / "RI.tif"
    assert main(["reconstruct", str(acq), "--config", str(tmp_path / "cfg.json"), "--out", str(out), "--tv-family",
                 "--device", "cpu", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "TV family" in text and "(picked)" in text
    report = json.loads((tmp_path / "RI.json").read_text())
    family = report["regularisation"]["family"]
    assert [m["tau"] for m in family] == list(FAMILY_TAUS)
    picked = [m for m in family if m["picked"]]
    assert len(picked) == 1 and picked[0]["path"] == str(out)
    assert report["regularisation"]["tv_xy_weight"] == picked[0]["tv_xy_weight"]
    best = min(m["validation_error"] for m in family)
    assert picked[0]["validation_error"] <= 1.05 * best
    assert all(m["tau"] <= picked[0]["tau"] or m["validation_error"] > 1.05 * best for m in family)
    for m in family:
        assert Path(m["path"]).is_file()
        if not m["picked"]:
            assert Path(m["path"]) == member_path(out, m["tau"])
    assert not member_path(out, picked[0]["tau"]).exists()  # the pick lives at --out only
    # the first member's choice of model parts kept none: the later members ran with the parts off (no tests) ...
    first = json.loads(Path(family[0]["path"]).with_suffix(".json").read_text())
    assert first["model_parts"]["needed"] == [] and "validation" in first["model_parts"]["chosen_by"].values()
    assert [m["parts_shared_from"] for m in family] == [None, FAMILY_TAUS[0], FAMILY_TAUS[0]]
    # ... and a member is the cold run at its weight, bit for bit, its own tests included (they keep nothing either)
    other = next(m for m in family if not m["picked"] and m["parts_shared_from"] is not None)
    cold = tmp_path / "cold.tif"
    assert main(["reconstruct", str(acq), "--config", str(tmp_path / "cfg.json"), "--out", str(cold), "--device", "cpu", "--quiet",
                 "--tv-xy-weight", f"{other['tv_xy_weight']:g}", "--tv-z-weight", f"{other['tv_z_weight']:g}"]) == 0
    assert np.array_equal(read_volume_tiff(cold)[0], read_volume_tiff(other["path"])[0])
    # --config RI.json reruns the pick alone (its weights as numbers, no family)
    assert report["config"]["tv_family"] == "false"
    again = tmp_path / "again.tif"
    assert main(["reconstruct", "--config", str(tmp_path / "RI.json"), "--out", str(again), "--device", "cpu", "--quiet"]) == 0
    assert np.array_equal(read_volume_tiff(again)[0], read_volume_tiff(out)[0])
    assert "family" not in json.loads((tmp_path / "again.json").read_text())["regularisation"]


def test_fdt_plan_prices_the_family_as_its_members(tmp_path: Path, tiny_sim, capsys) -> None:
    acq = write_acquisition(tiny_sim.acquisition, tmp_path / "acq")
    assert main(["plan", str(acq), "--json"]) == 0
    one = json.loads(capsys.readouterr().out)
    assert main(["plan", str(acq), "--json", "--tv-family"]) == 0
    family = json.loads(capsys.readouterr().out)
    assert family["tv_family"]["taus"] == list(FAMILY_TAUS)
    member = family["tv_family"]["predicted_member_s"]
    assert family["tv_family"]["predicted_total_s"] == pytest.approx(len(FAMILY_TAUS) * member)
    assert member <= one["predicted_total_s"] * 1.001  # a member runs no TV trials: at most the run's own price
    assert main(["plan", str(acq), "--tv-family"]) == 0
    assert "a family of 3 volumes" in capsys.readouterr().out


def test_the_familys_price_is_a_range_where_its_members_choose_model_parts() -> None:
    """Where model parts are to choose, ``fdt plan --tv-family`` says what the family costs where the data ask for
    none and up to what the costliest choices make of every member (the cells scene's geometry, as recorded in
    ``benchmarks/results/plan_range_cpu.json``)."""
    from benchmarks.plan_range import recorded_acquisition
    from napari_fdt.cli.family import family_json, family_summary, planned_config
    from napari_fdt.recon.loop.plan import plan_for

    run = json.loads((Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "plan_range_cpu.json").read_text())["runs"][1]
    acq = recorded_acquisition(run)
    plan, _ = plan_for(acq, planned_config(SolverConfig(), True), "cpu")
    assert plan.if_part_kept_s and plan.most_s > plan.predicted_s
    entry = family_json(True, plan)["tv_family"]
    assert entry["predicted_total_s_if_the_costliest_parts_are_kept"] == pytest.approx(len(FAMILY_TAUS) * plan.most_s)
    assert "in all where the data ask for no model part, up to about" in family_summary(True, plan).splitlines()[0]


def test_a_family_interrupted_resumes_from_its_checkpoints_to_the_same_volumes(tmp_path: Path, scene16, capsys) -> None:
    """A family stopped inside its second member (after that member's first stage) and resumed with ``--resume`` of its
    checkpoint folder writes the same members, bit for bit, as the family run without a stop: the first member
    continues from its last checkpoint (no more iterations), the second from its first stage's, the third starts."""
    from napari_fdt.data.io import read_acquisition
    from napari_fdt.recon.run.family import FAMILY_MARKER, member_folder, read_family_marker, run_family

    acq = write_acquisition(scene16.acquisition, tmp_path / "acq")
    cfg = _short()
    cfg.save(tmp_path / "cfg.json")
    full = tmp_path / "full" / "RI.tif"
    full.parent.mkdir()
    assert main(["reconstruct", str(acq), "--config", str(tmp_path / "cfg.json"), "--out", str(full), "--tv-family",
                 "--device", "cpu", "--quiet"]) == 0

    ck, stop = tmp_path / "ck", [False]
    runs = run_family(read_acquisition(acq), SolverConfig.from_dict({**cfg.to_dict(), "tv_family": "true"}), device="cpu",
                      should_stop=lambda: stop[0], checkpoint_dir=ck)
    with pytest.raises(StopIteration) as ended:
        while True:
            k, snap = next(runs)
            if k == 1 and snap.stage_complete:
                stop[0] = True  # inside the second member, after its first stage: as a killed run
    assert ended.value.value is None  # stopped: no family
    assert read_family_marker(ck)[1] == tuple(FAMILY_TAUS) and (ck / FAMILY_MARKER).is_file()
    assert (member_folder(ck, FAMILY_TAUS[1]) / "stage_0.pt").is_file()
    assert not member_folder(ck, FAMILY_TAUS[2]).exists()

    resumed = tmp_path / "resumed" / "RI.tif"
    resumed.parent.mkdir()
    capsys.readouterr()
    assert main(["reconstruct", str(acq), "--resume", str(ck), "--out", str(resumed), "--device", "cpu", "--quiet"]) == 0
    assert "resuming the family" in capsys.readouterr().err
    for tau in FAMILY_TAUS:
        a = member_path(full, tau) if member_path(full, tau).exists() else full
        b = member_path(resumed, tau) if member_path(resumed, tau).exists() else resumed
        assert (a == full) == (b == resumed)  # the same member picked
        assert np.array_equal(read_volume_tiff(a)[0], read_volume_tiff(b)[0]), tau
    assert (member_folder(ck, FAMILY_TAUS[2]) / "stage_1.pt").is_file()  # the resumed family went on writing there


def test_members_start_with_the_parts_the_first_member_kept_and_are_its_cold_runs(tmp_path: Path) -> None:
    """Data made with 4 screens per slice (tests/test_parts_branch.py's scene): the first member keeps sub-slices (by the
    branch) and runs every stage again with them; the next member starts with them on from its first stage (multi-slice
    coarse stages, the other parts still tried at its finest stage's end), so it runs each stage once. Its volume is the
    cold run's at its weight bit for bit: a cold run's second pass also starts from the state before any stage."""
    from test_parts_backward import _acquisition, _config

    from napari_fdt.recon.loop.phases import RERUN
    from napari_fdt.recon.run.family import run_family
    from napari_fdt.recon.run.report import describe_parts, model_parts_summary
    from napari_fdt.recon.run.solver import Reconstructor

    acq, cfg = _acquisition(sub_slices=4), _config(sub_slices="auto")
    runs = run_family(acq, cfg, device="cpu", taus=(1.0, 3.0))
    with pytest.raises(StopIteration) as ended:
        while True:
            next(runs)
    first, member = ended.value.value.members
    assert first.rec.parts["sub_slices"] and first.rec.parts_choice.rerun == "stages" and first.parts_shared == []
    assert member.parts_shared == ["sub_slices"] and member.parts_shared_from == 1.0 and member.rec.parts["sub_slices"]
    assert member.rec.parts_choice.rerun == "before" and not any(p.pass_name == RERUN for p in member.rec.plan.phases)
    tried = [(t["part"], t.get("pass")) for t in member.rec.parts_choice.trials if "shared_from" not in t]
    assert tried == [("aberrations", 1)]  # the parts not kept, tried at its finest stage's end
    assert "as the family's τ 1 member kept them" in describe_parts(model_parts_summary(member.rec))
    cold = Reconstructor(acq, member_config(cfg, 3.0), device="cpu")
    for _ in cold.run():
        pass
    assert cold.parts_choice.rerun == "stages" and any(p.pass_name == RERUN for p in cold.plan.phases)
    assert np.array_equal(cold.delta_n_full(), member.rec.delta_n_full())
    assert member.validation_error == pytest.approx(cold.stages[-1].validation_error, rel=1e-6)
