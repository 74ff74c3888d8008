"""Outputs and hand-off: report names, OME-Zarr volumes, the writer's contract, the `fdt reconstruct` line that
reproduces a run, reruns from a report, and flows run twice that must lose nothing."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest

from napari_fdt import Optics, simulate, source_grid, write_acquisition
from napari_fdt.cli import _config_from_args, _progress_bar, build_parser, main
from napari_fdt.data.io import read_acquisition, read_volume_tiff, report_path
from napari_fdt.errors import FDTInputError
from napari_fdt.napari.layers import META_KIND, META_REPORT
from napari_fdt.napari.reader import get_reader
from napari_fdt.napari.writer import write_ri
from napari_fdt.recon.run.solver import Reconstructor
from napari_fdt.recon.settings.command import config_from_file, format_command, reconstruct_command
from napari_fdt.recon.settings.config import SolverConfig, StageConfig
from napari_fdt.sim.phantoms import text_phantom

REPORT = {"format": "napari-fdt-report", "version": 1, "ri": {"voxel_size_um": [2.0, 0.33, 0.33]}}


@pytest.fixture(scope="module")
def tiny():
    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=3, slice_spacing_um=2.0)
    return simulate(text_phantom((24, 24), 3, text="U", delta_n=0.05), o, source_grid(2, 4.0, 12.0), seed=2, device="cpu")


def _ri(shape=(3, 10, 12)) -> np.ndarray:
    return (1.33 + 0.01 * np.random.default_rng(0).random(shape)).astype(np.float32)


# --------------------------------------------------------------------------- report names


@pytest.mark.parametrize("volume, report", [
    ("RI.tif", "RI.json"), ("RI.ome.tif", "RI.json"), ("RI.OME.TIFF", "RI.json"), ("RI.ome.zarr", "RI.json"),
    ("RI_lr0.05.tif", "RI_lr0.05.json"), ("RI_lr0.05.ome.tif", "RI_lr0.05.json"), ("my.run.v2.tiff", "my.run.v2.json"),
    ("RI", "RI.json"), ("RI.data", "RI.data.json"),
])
def test_report_name_keeps_the_full_output_name(volume, report) -> None:
    assert report_path(Path("/x") / volume) == Path("/x") / report


def test_distinct_outputs_get_distinct_reports() -> None:
    names = [f"RI_lr0.{k:02d}{end}" for k in range(1, 30) for end in (".tif",)] + ["RI_a.b.tif", "RI_a.c.tif", "RI_a.tif"]
    assert len({report_path(n) for n in names}) == len(names)


# --------------------------------------------------------------------------- OME-Zarr


def test_ome_zarr_volume_follows_ngff_and_reads_back_with_zarr(tmp_path) -> None:
    zarr = pytest.importorskip("zarr")
    from napari_fdt.data.ome_zarr import read_volume_zarr, write_volume_zarr

    ri = _ri((3, 10, 12))
    write_volume_zarr(tmp_path / "RI.ome.zarr", ri, (2.0, 0.33, 0.25))
    # independent reading: zarr's own group and the NGFF 0.4 attributes as the specification names them
    group = zarr.open_group(str(tmp_path / "RI.ome.zarr"), mode="r")
    [ms] = group.attrs["multiscales"]
    assert ms["version"] == "0.4"
    assert [(a["name"], a["type"], a["unit"]) for a in ms["axes"]] == [(a, "space", "micrometer") for a in "zyx"]
    [ds] = ms["datasets"]
    scale, translation = ds["coordinateTransformations"]
    assert scale == {"type": "scale", "scale": [2.0, 0.33, 0.25]}
    # voxel (0, 0, 0)'s centre: z = dz/2 above the bottom face, x and y from the image centre (docs/format.md)
    assert translation["type"] == "translation" and np.allclose(translation["translation"], [1.0, -5 * 0.33, -6 * 0.25])
    assert np.array_equal(np.asarray(group[ds["path"]]), ri)
    vol, voxel, shift = read_volume_zarr(tmp_path / "RI.ome.zarr")
    assert np.array_equal(vol, ri) and np.allclose(voxel, (2.0, 0.33, 0.25)) and np.allclose(shift, (1.0, -1.65, -1.5))
    with pytest.raises(FDTInputError, match="exists"):
        write_volume_zarr(tmp_path / "RI.ome.zarr", ri, (2.0, 0.33, 0.25))


def test_ome_zarr_volume_opens_with_ome_zarr_py(tmp_path) -> None:
    """ome-zarr-py's reader (what napari-ome-zarr uses) finds the image, its axes and transformations, and the pixels."""
    pytest.importorskip("ome_zarr")
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Multiscales, Reader

    from napari_fdt.data.ome_zarr import write_volume_zarr

    ri = _ri((3, 10, 12))
    write_volume_zarr(tmp_path / "RI.ome.zarr", ri, (2.0, 0.33, 0.25))
    [node] = list(Reader(parse_url(str(tmp_path / "RI.ome.zarr")))())
    assert any(isinstance(spec, Multiscales) for spec in node.specs)
    assert [a["name"] for a in node.metadata["axes"]] == ["z", "y", "x"]
    [[scale, translation]] = node.metadata["coordinateTransformations"]
    assert scale["scale"] == [2.0, 0.33, 0.25] and np.allclose(translation["translation"], [1.0, -5 * 0.33, -6 * 0.25])
    assert np.array_equal(np.asarray(node.data[0]), ri)


def test_napari_writer_and_reader_round_trip_ome_zarr(tmp_path) -> None:
    pytest.importorskip("zarr")
    ri = _ri()
    written = write_ri(str(tmp_path / "RI_lr0.05.ome.zarr"), ri, {"scale": (2.0, 0.33, 0.33), "metadata": {META_REPORT: REPORT}})
    assert written == [str(tmp_path / "RI_lr0.05.ome.zarr"), str(tmp_path / "RI_lr0.05.json")]
    reader = get_reader(str(tmp_path / "RI_lr0.05.ome.zarr"))
    [(data, kwargs, kind)] = reader(str(tmp_path / "RI_lr0.05.ome.zarr"))
    assert np.array_equal(data, ri) and np.allclose(kwargs["scale"], (2.0, 0.33, 0.33))
    assert np.allclose(kwargs["translate"], (1.0, -5 * 0.33, -6 * 0.33)) and kwargs["name"] == "RI_lr0.05"
    assert kwargs["metadata"][META_KIND] == "ri" and kwargs["metadata"][META_REPORT]["output"].endswith("RI_lr0.05.ome.zarr")


def test_reconstruct_writes_ome_zarr(tiny, tmp_path, capsys) -> None:
    pytest.importorskip("zarr")
    from napari_fdt.data.ome_zarr import read_volume_zarr

    acq_dir = write_acquisition(tiny.acquisition, tmp_path / "acq")
    cfg = tmp_path / "cfg.json"
    SolverConfig(stages=[StageConfig(factor=1, iterations=2)], snapshot_every=1).save(cfg)
    assert main(["reconstruct", str(acq_dir), "--out", str(tmp_path / "RI.ome.zarr"), "--config", str(cfg), "--quiet", "--device", "cpu"]) == 0
    vol, voxel, _ = read_volume_zarr(tmp_path / "RI.ome.zarr")
    assert vol.shape == (3, 24, 24) and np.allclose(voxel, (2.0, 0.33, 0.33))
    assert json.loads((tmp_path / "RI.json").read_text())["output"] == str(tmp_path / "RI.ome.zarr")


# --------------------------------------------------------------------------- the writer's contract


def test_writer_refuses_image_stacks_before_writing(tmp_path) -> None:
    stack = np.ones((5, 16, 16), np.float32)
    for kind in ("stack", "acquisition", None):
        with pytest.raises(FDTInputError, match=r"^layer: .* not an RI volume"):
            write_ri(str(tmp_path / "s.tif"), stack, {"name": "cells", "scale": (1, 0.3, 0.3), "metadata": {META_KIND: kind}})
    assert list(tmp_path.iterdir()) == []
    # RI layers without a report are written (a ground truth), with a suffix when the name has none
    written = write_ri(str(tmp_path / "truth"), _ri(), {"scale": (2.0, 0.33, 0.33), "metadata": {META_KIND: "truth"}})
    assert written == [str(tmp_path / "truth.ome.tif")]


def test_saves_over_similar_names_leave_earlier_work_intact(tmp_path) -> None:
    a, b = _ri(), _ri() + np.float32(0.01)
    write_ri(str(tmp_path / "RI_lr0.05.tif"), a, {"scale": (2.0, 0.33, 0.33), "metadata": {META_REPORT: {**REPORT, "run": 1}}})
    write_ri(str(tmp_path / "RI_lr0.07.tif"), b, {"scale": (2.0, 0.33, 0.33), "metadata": {META_REPORT: {**REPORT, "run": 2}}})
    assert json.loads((tmp_path / "RI_lr0.05.json").read_text())["run"] == 1
    assert json.loads((tmp_path / "RI_lr0.07.json").read_text())["run"] == 2
    assert np.array_equal(read_volume_tiff(tmp_path / "RI_lr0.05.tif")[0], a)
    # RI.ome.tif would share RI_lr0.05.json with RI_lr0.05.tif: refused, the first report untouched
    with pytest.raises(FDTInputError, match=r"^out: .*RI_lr0.05.json is the report of RI_lr0.05.tif"):
        write_ri(str(tmp_path / "RI_lr0.05.ome.tif"), b, {"scale": (2.0, 0.33, 0.33), "metadata": {META_REPORT: {**REPORT, "run": 3}}})
    assert json.loads((tmp_path / "RI_lr0.05.json").read_text())["run"] == 1
    assert not (tmp_path / "RI_lr0.05.ome.tif").exists()
    # a layer without a report saved over a volume with one: refused, not left with a stale report
    with pytest.raises(FDTInputError, match="report of the volume this save replaces"):
        write_ri(str(tmp_path / "RI_lr0.05.tif"), b, {"scale": (2.0, 0.33, 0.33), "metadata": {META_KIND: "ri"}})
    assert np.array_equal(read_volume_tiff(tmp_path / "RI_lr0.05.tif")[0], a)
    # the reader attaches a report only to the volume it names
    [(_, kwargs, _)] = get_reader(str(tmp_path / "RI_lr0.07.tif"))(str(tmp_path / "RI_lr0.07.tif"))
    assert kwargs["metadata"][META_REPORT]["run"] == 2


def test_write_acquisition_keeps_edited_sources_and_optics_and_never_overwrites(tiny, tmp_path) -> None:
    from dataclasses import replace

    acq = tiny.acquisition
    edited = acq.sources_um + np.array([0.5, -0.25, 1.0])
    optics = replace(acq.optics, na=0.7, image_plane_um=1.5)
    from napari_fdt.data.acquisition import Acquisition

    new = Acquisition(images=acq.images, optics=optics, sources_um=edited, extra={"note": "edited in napari"})
    write_acquisition(new, tmp_path / "saved")
    back = read_acquisition(tmp_path / "saved")
    assert back.optics == optics and np.array_equal(back.sources_um, edited) and np.array_equal(back.images, acq.images)
    assert back.extra["note"] == "edited in napari"
    before = (tmp_path / "saved" / "acquisition.json").read_bytes()
    with pytest.raises(FDTInputError, match="exists"):
        write_acquisition(acq, tmp_path / "saved")
    assert (tmp_path / "saved" / "acquisition.json").read_bytes() == before


# --------------------------------------------------------------------------- hand-off


def test_command_flags_reproduce_the_settings() -> None:
    cfg = SolverConfig(lr_ri=0.07, calibrate_gain=False, coherence="mask", mask_threshold=0.4, seed=5, tv_xy_weight=1e-4)
    argv = reconstruct_command("acq dir", "out/RI_lr0.07.tif", cfg, device="cuda")
    assert argv[:5] == ["fdt", "reconstruct", "acq dir", "--out", "out/RI_lr0.07.tif"]
    args = build_parser().parse_args(argv[1:])
    assert _config_from_args(args) == cfg and args.device == "cuda" and str(args.acquisition) == "acq dir"
    assert "'acq dir'" in format_command(argv)
    # an explicit seed replaces the settings' seed, once
    argv = reconstruct_command("a", "RI.tif", cfg, seed=9)
    assert argv.count("--seed") == 1 and _config_from_args(build_parser().parse_args(argv[1:])).seed == 9
    # stages have no flag: the settings must travel in a file
    with pytest.raises(FDTInputError, match=r"^config: stages differs"):
        reconstruct_command("a", "RI.tif", SolverConfig(stages=[StageConfig(factor=1, iterations=3)]))
    assert reconstruct_command("a", "RI.tif", "cfg.json")[5:7] == ["--config", "cfg.json"]


def test_saved_acquisition_and_command_reproduce_the_run(tiny, tmp_path, capsys) -> None:
    """What the widget does in memory (edited sources, its settings, a seed) = saving the acquisition and running
    the command line built for it: the same volume to float tolerance (CPU, fixed seed)."""
    acq = tiny.acquisition
    from napari_fdt.data.acquisition import Acquisition

    edited = Acquisition(images=acq.images, optics=acq.optics, sources_um=acq.sources_um + np.array([0.2, 0.0, 0.5]))
    cfg = SolverConfig(stages=[StageConfig(factor=2, iterations=3), StageConfig(factor=1, iterations=3)], snapshot_every=1, seed=4)
    rec = Reconstructor(edited, cfg, device="cpu")
    for _ in rec.run():
        pass
    in_memory = rec.ri_full()
    folder = write_acquisition(edited, tmp_path / "saved")
    cfg_path = tmp_path / "settings.json"
    cfg.save(cfg_path)
    argv = reconstruct_command(folder, tmp_path / "RI.tif", cfg_path, seed=4, device="cpu")
    assert main(argv[1:] + ["--quiet"]) == 0
    vol, _ = read_volume_tiff(tmp_path / "RI.tif")
    assert np.allclose(vol, in_memory, atol=1e-5), np.abs(vol - in_memory).max()
    # rerun from the report: its settings and acquisition, into another name
    report = tmp_path / "RI.json"
    assert config_from_file(report) == cfg
    assert main(["reconstruct", "--config", str(report), "--out", str(tmp_path / "RI_rerun.tif"), "--quiet", "--device", "cpu"]) == 0
    assert np.allclose(read_volume_tiff(tmp_path / "RI_rerun.tif")[0], in_memory, atol=1e-5)
    # the report read as --config is an input: never the output's report
    capsys.readouterr()
    assert main(["reconstruct", "--config", str(report), "--out", str(tmp_path / "RI.tif"), "--overwrite", "--quiet"]) == 2
    assert "would overwrite an input" in capsys.readouterr().err


def test_cli_run_twice_over_similar_names_loses_nothing(tiny, tmp_path, capsys) -> None:
    acq_dir = write_acquisition(tiny.acquisition, tmp_path / "acq")
    base = ["reconstruct", str(acq_dir), "--quiet", "--device", "cpu"]
    cfg = tmp_path / "cfg.json"
    SolverConfig(stages=[StageConfig(factor=1, iterations=2)], snapshot_every=1).save(cfg)
    assert main(base + ["--config", str(cfg), "--out", str(tmp_path / "RI_lr0.05.tif"), "--lr-ri", "0.05"]) == 0
    assert main(base + ["--config", str(cfg), "--out", str(tmp_path / "RI_lr0.07.tif"), "--lr-ri", "0.07"]) == 0
    r5 = json.loads((tmp_path / "RI_lr0.05.json").read_text())
    r7 = json.loads((tmp_path / "RI_lr0.07.json").read_text())
    assert r5["config"]["lr_ri"] == 0.05 and r7["config"]["lr_ri"] == 0.07
    first = (tmp_path / "RI_lr0.05.tif").read_bytes()
    capsys.readouterr()
    # the same name again: refused without --overwrite; RI_lr0.05.ome.tif: refused even with it (shares the report)
    assert main(base + ["--config", str(cfg), "--out", str(tmp_path / "RI_lr0.05.tif")]) == 2
    assert main(base + ["--config", str(cfg), "--out", str(tmp_path / "RI_lr0.05.ome.tif"), "--overwrite"]) == 2
    assert "is the report of RI_lr0.05.tif" in capsys.readouterr().err
    assert (tmp_path / "RI_lr0.05.tif").read_bytes() == first and json.loads((tmp_path / "RI_lr0.05.json").read_text()) == r5


# --------------------------------------------------------------------------- progress


class _Pipe(io.StringIO):
    def isatty(self) -> bool:
        return False


def test_progress_in_a_log_is_plain_lines() -> None:
    out = _Pipe()
    bar = _progress_bar(10, disable=False, stream=out)
    bar.mininterval = 0  # every update shows (30 s in a real run)
    for i in range(10):
        bar.update(1)
    bar.write("stage 1/1 complete", file=bar.fp)
    bar.close()
    text = out.getvalue()
    assert "\r" not in text and "\x1b" not in text and text.isascii()
    lines = text.splitlines()
    assert any("10/10" in line for line in lines) and "stage 1/1 complete" in lines


def test_progress_grows_but_never_starts_again_when_the_stages_run_again_with_model_parts() -> None:
    """A run whose model-parts choice kept a part runs every stage again: the plan appends those phases, the bar's total
    grows and its count goes on from where it was, named by the phase."""
    from types import SimpleNamespace

    from napari_fdt.cli import _show_progress

    bar = _progress_bar(10, disable=False, stream=_Pipe())

    def snap(done: int, of: int, name: str) -> SimpleNamespace:
        return SimpleNamespace(losses={"total": 1.0}, validation_error=0.1, eta_s=1.0, stage_complete=False, tv_weights=None,
                               plan_iteration=done, plan_iterations=of, phase_name=name)

    _show_progress(bar, snap(8, 10, "stage 2/2 (x1)"))
    assert bar.n == 8 and "again" not in bar.desc
    _show_progress(bar, snap(13, 20, "stage 1/2 (x2) again with aberrations"))
    assert bar.n == 13 and bar.total == 20 and "again with aberrations" in bar.desc
    bar.close()


def test_command_for_folder_refuses_what_the_folder_does_not_hold(tiny_dir: Path) -> None:
    """The widget's Copy command without the widget (recon.command.command_for_folder): the line is given only for a
    folder that holds the optics and sources the run uses; settings go beside it under a new name each time."""
    import dataclasses
    import shlex

    from napari_fdt.recon.settings.command import command_for_folder

    acq = read_acquisition(tiny_dir)
    config = SolverConfig(stages=[StageConfig(1, 5)], seed=3)
    command, settings = command_for_folder(tiny_dir, acq.optics, acq.sources_um, config, device="cpu")
    assert settings == tiny_dir.with_name("tiny_settings.json") and SolverConfig.from_dict(
        json.loads(settings.read_text())).seed == 3
    argv = shlex.split(command)
    args = build_parser().parse_args(argv[1:])
    assert Path(args.acquisition) == tiny_dir and Path(args.config) == settings and args.device == "cpu"
    _, again = command_for_folder(tiny_dir, acq.optics, acq.sources_um, config)
    assert again == tiny_dir.with_name("tiny_settings_2.json")  # nothing overwritten
    with pytest.raises(FDTInputError, match="differ from"):
        command_for_folder(tiny_dir, dataclasses.replace(acq.optics, na=0.7), acq.sources_um, config)
    with pytest.raises(FDTInputError, match="differ from"):
        command_for_folder(tiny_dir, acq.optics, acq.sources_um + 0.5, config)
    with pytest.raises(FDTInputError, match="not an acquisition folder"):
        command_for_folder(None, acq.optics, acq.sources_um, config)
