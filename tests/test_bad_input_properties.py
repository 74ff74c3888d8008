"""Property-based bad input: whatever a user writes, the error is an FDTInputError naming a field, never a crash.

The core (configuration, acquisition.json, image stacks), then the command line (``fdt info`` and ``fdt
reconstruct`` called in-process) and napari's readers on corrupted acquisition folders: one line naming the
field, exit status 2, no traceback, or an accepted input read without losing a pixel. The widget half runs in
``tests/test_napari_plugin_more.py`` (it needs Qt).
"""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, assume, event, given, settings
from hypothesis import strategies as st

from napari_fdt.cli import main
from napari_fdt.data.io import read_acquisition
from napari_fdt.errors import FDTInputError, FDTWarning
from napari_fdt.physics.optics import OPTICS_FIELDS
from napari_fdt.recon.settings.config import SolverConfig, StageConfig

# Any JSON value a user could write.
json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3),
    max_leaves=6,
)
def _accepted(call):
    """``call()``'s result, or None once the refusal is checked: an FDTInputError whose message starts with its field."""
    try:
        return call()
    except FDTInputError as exc:
        assert exc.field and str(exc).startswith(exc.field)
        return None


config_keys = st.sampled_from(sorted(SolverConfig().to_dict()) + ["learning_rate", "stage", ""])


@settings(max_examples=150, deadline=None)
@given(st.dictionaries(config_keys, json_values, max_size=4))
def test_any_configuration_is_accepted_or_refused_with_a_named_field(data: dict) -> None:
    cfg = _accepted(lambda: SolverConfig.from_dict(data))
    if cfg is None:
        return
    # accepted: it must survive a JSON round trip unchanged
    assert SolverConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))).to_dict() == cfg.to_dict()


GOOD = {"format": "fdt-acquisition", "version": 1, "images": "images.tif", "wavelength_um": 0.635, "n_background": 1.33,
        "na": 0.8, "pixel_size_um": 0.33, "n_slices": 4, "slice_spacing_um": 2.0, "image_plane_um": 0.0,
        "sources_um": [[0.0, 0.0, 20.0], [1.0, 1.0, 20.0]]}


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=st.sampled_from(sorted(GOOD)), value=json_values, drop=st.booleans())
def test_any_corrupted_acquisition_json_fails_cleanly(tmp_path: Path, key: str, value, drop: bool) -> None:
    folder = tmp_path / "acq"
    folder.mkdir(exist_ok=True)
    tifffile.imwrite(folder / "images.tif", np.ones((2, 16, 16), np.float32))
    meta = dict(GOOD)
    if drop:
        meta.pop(key)
    else:
        meta[key] = value
    (folder / "acquisition.json").write_text(json.dumps(meta))
    acq = _accepted(lambda: read_acquisition(folder))
    if acq is None:
        return
    # accepted: the optics are physical and the sources consistent
    o = acq.optics
    assert 0 < o.na < o.n_background and o.pixel_size_um > 0 and o.n_slices >= 1
    assert acq.sources_um is None or acq.sources_um.shape == (2, 3)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(shape=st.lists(st.integers(0, 20), min_size=1, max_size=4),
       dtype=st.sampled_from(["float32", "float64", "uint8", "uint16", "int16", "int32", "complex64", "bool"]),
       bad=st.sampled_from([None, np.nan, np.inf, -1.0]))
def test_any_image_stack_is_read_or_refused_with_a_named_field(tmp_path: Path, shape, dtype: str, bad) -> None:
    folder = tmp_path / "acq2"
    folder.mkdir(exist_ok=True)
    arr = np.ones(shape, dtype=dtype)
    if bad is not None and arr.dtype.kind == "f" and arr.size:
        arr.flat[0] = bad
    try:
        tifffile.imwrite(folder / "images.tif", arr)
    except Exception:  # tifffile itself cannot write this array (e.g. empty): not a reader question
        assume(False)
    meta = dict(GOOD)
    meta.pop("sources_um")
    (folder / "acquisition.json").write_text(json.dumps(meta))
    acq = _accepted(lambda: read_acquisition(folder))
    if acq is None:
        return
    assert acq.images.ndim == 3 and min(acq.images.shape[1:]) >= 8
    if acq.images.dtype.kind == "f":
        assert np.isfinite(acq.images).all()


# -- the command line: fdt info and fdt reconstruct on corrupted acquisition folders ---------------------------

#: Every field a refusal of an acquisition folder may name (sources_um[i] too).
FIELDS = {"path", "acquisition.json", "format", "version", "images", "sources_um", *OPTICS_FIELDS}
_REQUIRED = {"format", "version", "images", "wavelength_um", "n_background", "na", "pixel_size_um", "n_slices",
             "slice_spacing_um"}
_ERROR = re.compile(r"^error: (?P<field>[^:]+): \S")


def _good_images() -> np.ndarray:
    return (1.0 + np.random.default_rng(0).random((2, 16, 16))).astype(np.float32)


def _tiff_bytes(arr: np.ndarray) -> bytes:
    import io as _io

    buf = _io.BytesIO()
    tifffile.imwrite(buf, arr, photometric="minisblack")
    return buf.getvalue()


@st.composite
def corrupted_folders(draw):
    """(kind, acquisition.json text, images.tif bytes, the field a refusal must name or None if it may be accepted)."""
    kind = draw(st.sampled_from(["value", "drop", "unknown_key", "json_syntax", "bad_pixel", "stack", "n_sources",
                                 "na_not_below_n_b", "size_not_positive", "truncated_tiff", "not_tiff"]))
    meta, images, expect = dict(GOOD), _good_images(), None
    tiff = None
    if kind == "value":
        key = draw(st.sampled_from(sorted(GOOD)))
        meta[key] = draw(json_values)
    elif kind == "drop":
        key = draw(st.sampled_from(sorted(GOOD)))
        meta.pop(key)
        expect = key if key in _REQUIRED else None
    elif kind == "unknown_key":
        meta[draw(st.text(min_size=1, max_size=8).filter(lambda k: k not in GOOD))] = draw(json_values)
    elif kind == "bad_pixel":
        bad = draw(st.sampled_from([np.nan, np.inf, -np.inf, -1.0]))
        images[draw(st.integers(0, 1)), draw(st.integers(0, 15)), draw(st.integers(0, 15))] = bad
        expect = None if bad == -1.0 else "images"  # a negative pixel is accepted with a warning
    elif kind == "stack":
        shape = draw(st.lists(st.integers(0, 20), min_size=2, max_size=4))
        dtype = draw(st.sampled_from(["float32", "float64", "uint8", "uint16", "int16", "int32", "complex64", "bool"]))
        images = np.ones(shape, dtype=dtype)
        meta.pop("sources_um")
    elif kind == "n_sources":
        meta["sources_um"] = [[0.0, 0.0, 20.0]] * draw(st.integers(0, 5).filter(lambda k: k != 2))
        expect = "sources_um"
    elif kind == "na_not_below_n_b":
        n_b = draw(st.floats(1.0, 3.0))
        meta.update(n_background=n_b, na=n_b + draw(st.floats(0.0, 2.0)))
        expect = "na"
    elif kind == "size_not_positive":
        key = draw(st.sampled_from(["wavelength_um", "pixel_size_um", "slice_spacing_um", "n_slices"]))
        meta[key] = draw(st.integers(-5, 0) | st.floats(-1e3, 0.0))
        expect = key
    text = json.dumps(meta)
    if kind == "json_syntax":
        text = text[: draw(st.integers(0, len(text) - 1))]  # every proper prefix of an object is invalid JSON
        expect = "acquisition.json"
    if kind in ("truncated_tiff", "not_tiff"):
        full = _tiff_bytes(images)
        tiff = (full[: draw(st.integers(0, len(full) - 1))] if kind == "truncated_tiff" else
                draw(st.sampled_from([b"", b"hello, world", b"\x89PNG\r\n\x1a\n" + bytes(64), b"II*\x00" + b"\xff" * 16,
                                      b"MM\x00*" + bytes(4)])))
        expect = None if kind == "truncated_tiff" else "images"  # a cut through unused bytes can still read
    else:
        try:
            tiff = _tiff_bytes(images)
        except Exception:  # tifffile itself cannot write this array (e.g. empty): not a reader question
            assume(False)
    return kind, text, tiff, expect


def _check_napari_readers(folder: Path, cli_refusal: str | None) -> None:
    """napari's reader on the folder, and on its images.tif opened as a bare stack: layers holding exactly the
    file's pixels, or the core's FDTInputError, with the message ``fdt info`` printed; a TIFF the header shows
    is no stack is declined (None) rather than claimed."""
    from napari_fdt.data.microscope import read_stack
    from napari_fdt.napari.reader import get_reader

    for path in (folder, folder / "images.tif"):
        reader = get_reader(str(path))
        if reader is None:  # a TIFF declined from its header: exactly those the core cannot read as a stack
            assert path.name == "images.tif"
            with pytest.raises(FDTInputError) as refused:
                read_stack(path)
            assert refused.value.field == "images", str(refused.value)
            continue
        try:
            layers = reader(str(path))
        except FDTInputError as exc:
            assert exc.field in FIELDS or exc.field.startswith("sources_um["), str(exc)
            if path == folder:  # the folder reader stops where fdt info stopped (info also plans the window)
                assert cli_refusal is not None and cli_refusal == f"error: {exc}", (cli_refusal, str(exc))
            continue
        (data, kwargs, kind), = layers
        with tifffile.TiffFile(folder / "images.tif") as tif:
            pixels = tif.series[0].asarray()
        assert np.array_equal(data, pixels.reshape(data.shape).astype(data.dtype)) and np.isfinite(data).all()
        if path == folder:
            assert kind == "image" and kwargs["metadata"]["fdt_acquisition"].n_images == data.shape[0]


def _run_cli(capsys, args: list[str]) -> tuple[int, str, str]:
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("always", FDTWarning)  # every example shows its warnings
        rc = main(args)
    out, err = capsys.readouterr()
    return rc, out, err


def _check_refusal(rc: int, err: str, expect: str | None) -> str | None:
    """The refusal line (exit 2, one ``error: field: …`` line, warnings and the run's plan aside, no traceback), or None if
    accepted."""
    plan = re.search(r"^plan \(\w+\): .*(\n  .*)*", err, flags=re.M)  # fdt reconstruct's plan (printed when it runs)
    lines = (err if plan is None else err.replace(plan.group(0), "")).strip().splitlines()
    assert "Traceback" not in err
    assert all(line.startswith(("error: ", "warning: ")) for line in lines), err
    errors = [line for line in lines if line.startswith("error: ")]
    if rc == 0:
        assert not errors and expect is None, (expect, err)
        return None
    assert rc == 2 and len(errors) == 1, (rc, err)
    m = _ERROR.match(errors[0])
    assert m, errors[0]
    field = m["field"]
    assert field in FIELDS or re.fullmatch(r"sources_um\[\d+\]", field), field
    if expect is not None:
        assert field == expect or (expect == "sources_um" and field.startswith("sources_um")), (expect, errors[0])
    return errors[0]


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(case=corrupted_folders())
def test_cli_refuses_any_corrupted_acquisition_with_one_line(tmp_path: Path, capsys, case) -> None:
    """``fdt info`` and ``fdt reconstruct`` (in-process) on a corrupted folder: exit 2 and one line naming the field,
    the same line from both, or (where the corruption is harmless) a normal run that reads exactly the pixels written."""
    kind, text, tiff, expect = case
    folder = tmp_path / "acq"
    folder.mkdir(exist_ok=True)
    (folder / "acquisition.json").write_text(text, encoding="utf-8")
    (folder / "images.tif").write_bytes(tiff)
    rc, out, err = _run_cli(capsys, ["info", str(folder)])
    refusal = _check_refusal(rc, err, expect)
    event(f"{kind}: {'refused' if refusal else 'accepted'}")
    if kind == "bad_pixel" and refusal is None:
        assert "warning: images: 1 negative pixels" in err
    if kind == "truncated_tiff" and refusal is None:  # nothing lost: what was read is what was written
        assert np.array_equal(read_acquisition(folder).images, _good_images())
    _check_napari_readers(folder, refusal)
    config = tmp_path / "tiny.json"
    if not config.exists():
        SolverConfig(stages=[StageConfig(1, 1)], batch_size=2).save(config)
    window = re.search(r"forward window: (\d+)x(\d+) px", out)
    if refusal is None and (window is None or max(map(int, window.groups())) > 256):
        return  # accepted, but a big window (or a source fit) would make this example slow: fdt info is enough
    out_ri = tmp_path / "ri.tif"
    rc2, _, err2 = _run_cli(capsys, ["reconstruct", str(folder), "--out", str(out_ri), "--config", str(config),
                                     "--device", "cpu", "--quiet", "--overwrite"])
    refusal2 = _check_refusal(rc2, err2, expect)
    event(f"reconstruct {'refused' if refusal2 else 'ran'}")
    if refusal is not None:
        assert refusal2 == refusal  # the same input, the same message
    else:
        assert refusal2 is None or refusal2.startswith("error: images:"), refusal2  # e.g. blank images
        if refusal2 is None:
            from napari_fdt.data.io import read_volume_tiff

            assert np.isfinite(read_volume_tiff(out_ri)[0]).all()
