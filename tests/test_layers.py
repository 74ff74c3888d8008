"""The napari plugin's Qt-free parts: layer geometry, reader, writer, sample data, coverage, settings, the job.

None of these tests needs a display or Qt; the Qt tests are in ``test_napari_plugin.py`` and ``test_napari_plugin_more.py``.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import tifffile

from benchmarks.scenes import tiny_scene
from napari_fdt import Optics, write_acquisition
from napari_fdt.data.io import read_volume_tiff
from napari_fdt.errors import FDTInputError
from napari_fdt.napari.jobs.compute import forward_preview, illumination_coverage, mask_stack, predicted_vs_measured
from napari_fdt.napari.jobs.job import reconstruction_job
from napari_fdt.napari.layers import (
    META_ACQUISITION,
    META_NEEDS_OPTICS,
    META_REPORT,
    points_to_sources,
    sources_to_points,
    volume_scale,
    volume_translate,
)
from napari_fdt.napari.reader import get_reader
from napari_fdt.napari.sample_data import BEADS_NAME, LETTERS_NAME, letters_sample, sample_dir
from napari_fdt.napari.settings import format_stages, merge_config, parse_stages
from napari_fdt.napari.writer import write_ri
from napari_fdt.recon.run.solver import Reconstructor
from napari_fdt.recon.settings.config import SolverConfig, StageConfig

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tiny():
    """32×32 px, 4 slices, 9 sources: the plugin tests' scene."""
    return tiny_scene(grid=3, seed=1)


@pytest.fixture()
def tiny_dir(tiny, tmp_path) -> Path:
    return write_acquisition(tiny.acquisition, tmp_path / "tiny")


def test_core_imports_no_qt_or_napari() -> None:
    """The headless core and the plugin's Qt-free modules import neither napari nor a Qt binding."""
    code = (
        "import sys, napari_fdt, napari_fdt.recon.run.solver, napari_fdt.recon.run.report, napari_fdt.cli, napari_fdt.napari.layers, "
        "napari_fdt.napari.jobs.compute, napari_fdt.napari.jobs.job, napari_fdt.napari.settings, napari_fdt.napari.reader, napari_fdt.napari.writer, "
        "napari_fdt.napari.sample_data\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in "
        "('napari', 'magicgui', 'qtpy', 'PyQt5', 'PyQt6', 'PySide2', 'PySide6', 'vispy', 'superqt'))\n"
        "print(bad); sys.exit(1 if bad else 0)"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr


def test_sources_and_points_convention() -> None:
    src = np.array([[1.0, -2.0, 40.0], [0.5, 0.25, 12.0]])
    pts = sources_to_points(src)
    assert np.allclose(pts, [[-40.0, -2.0, 1.0], [-12.0, 0.25, 0.5]])  # (z, y, x), z = −depth
    assert np.allclose(points_to_sources(pts, 2), src)
    with pytest.raises(FDTInputError, match="holds 2 points for 3 images"):
        points_to_sources(pts, 3)
    with pytest.raises(FDTInputError, match=r"sources\[1\].*not below"):
        points_to_sources(np.array([[-1.0, 0, 0], [0.5, 0, 0]]))


def test_volume_placement_puts_voxel_centres_in_um() -> None:
    o = Optics(wavelength_um=0.6, n_background=1.33, na=0.8, pixel_size_um=0.5, n_slices=3, slice_spacing_um=2.0)
    assert volume_scale(o) == (2.0, 0.5, 0.5)
    # slice 0's centre at z = dz/2, pixel (H//2, W//2) at the lateral origin
    assert volume_translate(o, (8, 9)) == (1.0, -2.0, -2.0)


def test_illumination_coverage_follows_the_pupil_cone() -> None:
    o = Optics(wavelength_um=0.6, n_background=1.33, na=0.8, pixel_size_um=0.5, n_slices=2, slice_spacing_um=2.0)
    tan = math.tan(math.asin(0.8 / 1.33))
    cov = illumination_coverage(o, (41, 41), np.array([[0.0, 0.0, 10.0]]))
    assert cov.shape == (2, 41, 41) and cov.dtype == np.int32
    for k, z in enumerate((1.0, 3.0)):
        r = (10.0 + z) * tan
        ys, xs = np.nonzero(cov[k])
        radius = np.hypot((ys - 20) * 0.5, (xs - 20) * 0.5)
        assert radius.max() <= r + 1e-9
        # every pixel within the radius is lit
        yy, xx = np.mgrid[:41, :41]
        inside = np.hypot((yy - 20) * 0.5, (xx - 20) * 0.5) <= r
        assert np.array_equal(cov[k].astype(bool), inside)
    assert cov[1].sum() > cov[0].sum()  # the cone widens upwards
    two = illumination_coverage(o, (41, 41), np.array([[0.0, 0.0, 10.0], [3.0, 0.0, 10.0]]))
    assert two.max() == 2 and two[0, 20, 20] == 2 and two[0, 20, 40] == 1 and two[0, 20, 0] == 0


def test_reader_acquisition_folder(tiny, tiny_dir) -> None:
    reader = get_reader(str(tiny_dir))
    assert reader is not None
    assert get_reader(str(tiny_dir / "acquisition.json")) is not None
    [(data, kwargs, kind)] = reader(str(tiny_dir))
    # the image index on an axis of its own (unit pixel); one plane spanning the volume's z range (4 × 2 µm)
    assert kind == "image" and data.shape == (9, 1, 32, 32)
    assert np.shares_memory(data, kwargs["metadata"][META_ACQUISITION].images)  # a view, not a copy
    assert kwargs["scale"] == (1.0, 8.0, 0.33, 0.33) and kwargs["units"] == ("pixel", "µm", "µm", "µm")
    assert kwargs["axis_labels"] == ("image", "z", "y", "x")
    assert kwargs["translate"] == (0.0, 4.0, -16 * 0.33, -16 * 0.33)
    acq = kwargs["metadata"][META_ACQUISITION]
    assert acq.optics == tiny.acquisition.optics and kwargs["metadata"]["fdt_path"] == str(tiny_dir)


def test_reader_not_ours_and_broken(tmp_path, tiny_dir) -> None:
    (tmp_path / "empty").mkdir()
    assert get_reader(str(tmp_path / "empty")) is None
    (tmp_path / "notes.txt").write_text("x")
    assert get_reader(str(tmp_path / "notes.txt")) is None
    meta = json.loads((tiny_dir / "acquisition.json").read_text())
    meta["na"] = 1.5
    (tiny_dir / "acquisition.json").write_text(json.dumps(meta))
    reader = get_reader(str(tiny_dir))
    with pytest.raises(FDTInputError, match=r"^na: numerical aperture 1.5 is not below n_background 1.33"):
        reader(str(tiny_dir))


def test_reader_bare_stack_needs_optics(tmp_path) -> None:
    tifffile.imwrite(tmp_path / "stack.tif", np.ones((5, 16, 16), np.float32))
    [(data, kwargs, kind)] = get_reader(str(tmp_path / "stack.tif"))(str(tmp_path / "stack.tif"))
    assert data.shape == (5, 1, 16, 16) and kwargs["metadata"][META_NEEDS_OPTICS] is True
    assert kwargs["units"] == ("pixel",) * 4  # no optics: no µm claimed
    assert META_ACQUISITION not in kwargs["metadata"]
    tifffile.imwrite(tmp_path / "tiny.tif", np.ones((2, 4, 4), np.float32), photometric="minisblack")
    assert get_reader(str(tmp_path / "tiny.tif")) is None  # declined from the header: napari offers it to other readers


def test_writer_and_reader_round_trip_an_ri_volume(tmp_path) -> None:
    ri = (1.33 + 0.01 * np.random.default_rng(0).random((3, 10, 12))).astype(np.float32)
    report = {"format": "napari-fdt-report", "version": 1, "ri": {"voxel_size_um": [2.0, 0.33, 0.33]}}
    written = write_ri(str(tmp_path / "RI.ome.tif"), ri, {"scale": (2.0, 0.33, 0.33), "metadata": {META_REPORT: report}})
    assert written == [str(tmp_path / "RI.ome.tif"), str(tmp_path / "RI.json")]
    back, voxel = read_volume_tiff(tmp_path / "RI.ome.tif")
    assert np.array_equal(back, ri) and np.allclose(voxel, (2.0, 0.33, 0.33))
    assert json.loads((tmp_path / "RI.json").read_text())["output"] == str(tmp_path / "RI.ome.tif")
    [(data, kwargs, kind)] = get_reader(str(tmp_path / "RI.ome.tif"))(str(tmp_path / "RI.ome.tif"))
    assert np.array_equal(data, ri) and np.allclose(kwargs["scale"], (2.0, 0.33, 0.33))
    assert kwargs["metadata"][META_REPORT]["format"] == "napari-fdt-report"
    with pytest.raises(FDTInputError, match="not an RI volume"):
        write_ri(str(tmp_path / "flat.tif"), np.zeros((4, 4)), {"scale": (1, 1)})


def test_sample_data_names_and_content() -> None:
    manifest = (ROOT / "src" / "napari_fdt" / "napari" / "napari.yaml").read_text(encoding="utf-8")
    assert LETTERS_NAME in manifest and BEADS_NAME in manifest
    assert sample_dir() == ROOT / "sample_data" / "letters"
    layers = letters_sample()
    data, kwargs, _ = layers[0]
    acq = kwargs["metadata"][META_ACQUISITION]
    n, _, h, w = data.shape
    assert f"{n} images, {h}×{w}, {acq.optics.n_slices} slices" in LETTERS_NAME
    assert layers[1][0].shape == (acq.optics.n_slices, h, w) and layers[1][1]["visible"] is False


def test_stage_text_and_settings() -> None:
    assert parse_stages("4x100, 2×50,1:10") == [{"factor": 4, "iterations": 100}, {"factor": 2, "iterations": 50},
                                                {"factor": 1, "iterations": 10}]
    assert format_stages([StageConfig(4, 100), StageConfig(1, 5)]) == "4x100, 1x5"
    with pytest.raises(FDTInputError, match="^stages: cannot read 'four'"):
        parse_stages("four")
    with pytest.raises(FDTInputError, match="does not divide"):
        merge_config(SolverConfig(), {"stages": "4x10, 3x10"})
    cfg = merge_config(SolverConfig(lr_ri=0.07), {"stages": "2x3, 1x3", "seed": 5})
    assert cfg.lr_ri == 0.07 and cfg.seed == 5 and cfg.total_iterations == 6
    # a stage's own batch size survives the widget's text (settings loaded from a file are not lost)
    staged = [StageConfig(4, 100, 64), StageConfig(1, 5)]
    assert format_stages(staged) == "4x100@64, 1x5"
    assert merge_config(SolverConfig(), {"stages": format_stages(staged)}).stages == staged


def test_job_streams_throttles_and_cancel_keeps_the_last_complete_stage(tiny) -> None:
    cfg = SolverConfig(stages=[StageConfig(2, 3), StageConfig(1, 200)], batch_size=4, snapshot_every=1)
    stop = threading.Event()
    done = threading.Event()
    gen = reconstruction_job(tiny.acquisition, cfg, device="cpu", stop=stop, done=done, min_interval_s=3600.0)
    started = next(gen)
    assert started.kind == "started"
    rec = started.rec
    with_ri = []
    while True:
        u = next(gen)
        if u.ri is not None:
            with_ri.append(u.snapshot.stage)
        if u.snapshot.stage == 1 and u.snapshot.iteration >= 2:
            stop.set()
            break
    # throttled: the first snapshot, then only the stage end
    assert with_ri == [0, 0]
    rest = list(iter(lambda: next(gen, None), None))
    assert [u.kind for u in rest] == ["evaluating"]
    with pytest.raises(StopIteration):
        next(gen)
    assert done.is_set()
    # the returned result (re-run the end to get StopIteration.value)
    assert rec.completed_stages == 1
    expected = np.float32(1.33) + rec.last_complete.delta_n_full()
    assert np.allclose(rec.ri_full(), expected, atol=1e-6)


def test_job_result_after_cancel(tiny) -> None:
    cfg = SolverConfig(stages=[StageConfig(2, 2), StageConfig(1, 100)], batch_size=4, snapshot_every=1)
    stop = threading.Event()
    gen = reconstruction_job(tiny.acquisition, cfg, device="cpu", stop=stop)
    rec = next(gen).rec
    result = None
    try:
        while True:
            u = next(gen)
            if u.kind == "snapshot" and u.snapshot.stage == 1:
                stop.set()
    except StopIteration as end:
        result = end.value
    assert result.cancelled and result.completed_stages == 1
    assert np.allclose(result.ri, 1.33 + rec.last_complete.delta_n_full(), atol=1e-6)
    assert result.report["cancelled"] is True and result.report["completed_stages"] == 1


def test_previews(tiny) -> None:
    acq = tiny.acquisition
    pred, meas, gain = forward_preview(acq, tiny.sources_um, 4, tiny.ri - 1.33)
    assert pred.shape == meas.shape == (32, 32) and gain > 0
    assert np.linalg.norm(pred - meas) / np.linalg.norm(meas) < 0.2  # true RI and sources: noise level
    with pytest.raises(FDTInputError, match="^image: index 9"):
        forward_preview(acq, tiny.sources_um, 9)
    masks = mask_stack(acq, tiny.sources_um)
    assert masks.shape == (9, 32, 32) and set(np.unique(masks)) <= {0.0, 1.0} and masks.any()
    rec = Reconstructor(acq, SolverConfig(stages=[StageConfig(1, 2)], batch_size=4), device="cpu")
    for _ in rec.run():
        pass
    p, m = predicted_vs_measured(rec, 3)
    assert p.shape == m.shape == (32, 32) and np.isfinite(p).all()


def test_npe2_validate() -> None:
    npe2 = shutil.which("npe2", path=str(Path(sys.executable).parent))
    if npe2 is None:
        pytest.importorskip("npe2")
    cmd = [npe2, "validate", "napari-fdt"] if npe2 else [sys.executable, "-m", "npe2", "validate", "napari-fdt"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "valid" in r.stdout, r.stdout + r.stderr


def test_sample_ground_truth_is_not_the_reconstruction_layer() -> None:
    """A reconstruction updates the acquisition's "ri" layer; the sample's truth is a separate kind."""
    from napari_fdt.napari.sample_data import simulated_beads

    layers = simulated_beads()
    assert [kw["metadata"]["fdt_kind"] for _, kw, _ in layers] == ["acquisition", "truth"]


# -- the widgets' Qt-free parts: optics typed as text, the time-left estimate ----------------------------------------


def test_optics_entries_refuse_unit_mistakes_with_the_widget_labels() -> None:
    from napari_fdt.napari.settings import missing_optics, optics_from_entries

    good = dict(wavelength_um="0.635", n_background="1.33", na="0.8", pixel_size_um="0.33", n_slices="8",
                slice_spacing_um="2")
    assert optics_from_entries(good) == Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33,
                                               n_slices=8, slice_spacing_um=2.0)
    assert missing_optics({}) == ["emission wavelength (µm)", "medium refractive index", "objective NA",
                                  "pixel size in sample (µm)", "number of slices", "slice thickness (µm)"]
    cases = {
        ("wavelength_um", "635"): "emission wavelength (µm): 635 looks like nm, not µm (enter 0.635",
        ("wavelength_um", "6.35e-7"): "emission wavelength (µm): 6.35e-07 looks like m, not µm (enter 0.635",
        ("pixel_size_um", "330"): "pixel size in sample (µm): 330 looks like nm, not µm (enter 0.33",
        ("pixel_size_um", "0.00033"): "pixel size in sample (µm): 0.00033 looks like mm, not µm (enter 0.33",
        ("na", "1.4"): "objective NA: 1.4 is not below the medium refractive index 1.33 (an NA of 1.4 needs an "
                       "immersion index above it",
        ("na", "80"): "objective NA: 80 is not below the medium refractive index 1.33 (80 looks like an angle or a "
                      "percentage",
        ("n_slices", "2.5"): "number of slices: 2.5 is not a whole number",
        ("slice_spacing_um", "x"): "slice thickness (µm): 'x' is not a number",
        ("slice_spacing_um", "-1"): "slice thickness (µm): must be positive",
        ("n_background", ""): "medium refractive index: is empty",
        ("n_background", "0.5"): "medium refractive index: must be >= 1",
    }
    for (name, text), message in cases.items():
        with pytest.raises(FDTInputError) as exc:
            optics_from_entries({**good, name: text})
        assert str(exc.value).startswith(message), str(exc.value)


def test_optics_labels_are_plain_words_and_tooltips_name_the_field() -> None:
    """The acquisition widget labels each optics field in plain words with its unit; its tooltip starts with the
    field's name in the files and the API (``n_background: …``), so both vocabularies are on screen."""
    from napari_fdt.napari.settings import OPTICS_LABELS
    from napari_fdt.napari.widgets.widget_acquisition import OPTICS_TIPS
    from napari_fdt.physics.optics import OPTICS_FIELDS

    assert set(OPTICS_LABELS) == set(OPTICS_TIPS) == set(OPTICS_FIELDS)
    assert OPTICS_LABELS["n_background"] == "medium refractive index"
    for name in OPTICS_FIELDS:
        label = OPTICS_LABELS[name]
        assert "_" not in label and label.replace(" ", "_") != name, label
        assert label.endswith("(µm)") == name.endswith("_um"), label
        assert OPTICS_TIPS[name].startswith(f"{name}: "), OPTICS_TIPS[name]
