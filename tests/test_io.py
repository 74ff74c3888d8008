"""Tests of the acquisition folder (format version 1): reading, writing, checks, malformed folders (the RI volume's OME-TIFF: test_volume_io.py)."""

from __future__ import annotations

import hashlib
import json
import math
import tempfile
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from napari_fdt.data import io as fdt_io
from napari_fdt.data.acquisition import Acquisition
from napari_fdt.data.io import (
    read_acquisition,
    write_acquisition,
    write_json_atomic,
)
from napari_fdt.errors import FDTInputError, FDTWarning
from napari_fdt.physics.optics import Optics

REQUIRED_OPTICS = ("wavelength_um", "n_background", "na", "pixel_size_um", "n_slices", "slice_spacing_um")


def base_metadata(n: int = 3, *, sources: bool = True) -> dict[str, Any]:
    meta: dict[str, Any] = {
        "format": "fdt-acquisition",
        "version": 1,
        "images": "images.tif",
        "wavelength_um": 0.635,
        "n_background": 1.33,
        "na": 1.0,
        "pixel_size_um": 0.33,
        "n_slices": 14,
        "slice_spacing_um": 3.0,
        "image_plane_um": 0.0,
    }
    if sources:
        meta["sources_um"] = [[1.5 * i, -2.0 * i, 5.0 + i] for i in range(n)]
    return meta


def make_images(n: int = 3, h: int = 16, w: int = 12, dtype: Any = np.float32, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if np.dtype(dtype).kind == "u":
        return rng.integers(0, np.iinfo(dtype).max, size=(n, h, w), endpoint=True).astype(dtype)
    return rng.uniform(0.0, 1000.0, size=(n, h, w)).astype(dtype)


def make_acquisition(n: int = 3, dtype: Any = np.float32, *, sources: bool = True, seed: int = 0) -> Acquisition:
    meta = base_metadata(n, sources=sources)
    meta["operator"] = "A. N. Other"
    meta["stage"] = {"x_mm": 1.25, "tags": ["a", "µ", None, True]}
    return Acquisition.from_metadata(make_images(n, dtype=dtype, seed=seed), meta)


def write_raw_folder(folder: Path, meta: Any, images: np.ndarray | None = None, *, raw_json: str | None = None) -> Path:
    """An acquisition folder written by hand (not by ``write_acquisition``), possibly malformed."""
    folder.mkdir(parents=True, exist_ok=True)
    if images is not None:
        tifffile.imwrite(folder / "images.tif", images, photometric="minisblack")
    text = raw_json if raw_json is not None else json.dumps(meta, indent=1)
    (folder / "acquisition.json").write_text(text, encoding="utf-8")
    return folder


def folder_hashes(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def hidden_siblings(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name.startswith("."))


def assert_same_acquisition(a: Acquisition, b: Acquisition) -> None:
    assert a.images.dtype == b.images.dtype
    assert a.images.shape == b.images.shape
    # bit-exact, so -0.0 and subnormals count too
    assert a.images.tobytes() == b.images.tobytes()
    assert a.optics == b.optics
    if a.sources_um is None:
        assert b.sources_um is None
    else:
        assert b.sources_um is not None
        assert b.sources_um.dtype == np.float64
        np.testing.assert_array_equal(a.sources_um, b.sources_um)
    assert a.extra == b.extra


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("dtype", [np.float32, np.uint16])
def test_round_trip_identical(tmp_path: Path, dtype: Any) -> None:
    acq = make_acquisition(dtype=dtype)
    out = write_acquisition(acq, tmp_path / "acq")
    assert out == tmp_path / "acq"
    assert sorted(p.name for p in out.iterdir()) == ["acquisition.json", "images.tif"]
    back = read_acquisition(out)
    assert_same_acquisition(acq, back)
    assert back.images.dtype == np.dtype(dtype)
    assert back.n_images == 3 and back.image_shape == (16, 12)
    assert back.extra == {"operator": "A. N. Other", "stage": {"x_mm": 1.25, "tags": ["a", "µ", None, True]}}

    text = (out / "acquisition.json").read_text(encoding="utf-8")
    meta = json.loads(text)
    assert text.startswith('{\n "format": "fdt-acquisition"')  # indent=1
    assert meta["version"] == 1 and meta["images"] == "images.tif"
    assert all(isinstance(v, float) for row in meta["sources_um"] for v in row)
    # the stack is one (N, H, W) series
    with tifffile.TiffFile(out / "images.tif") as tif:
        assert tif.series[0].shape == (3, 16, 12)
        assert tif.series[0].dtype == np.dtype(dtype)


def test_read_accepts_json_path(tmp_path: Path) -> None:
    acq = make_acquisition()
    write_acquisition(acq, tmp_path / "acq")
    assert_same_acquisition(acq, read_acquisition(tmp_path / "acq" / "acquisition.json"))
    assert_same_acquisition(acq, read_acquisition(str(tmp_path / "acq")))


def test_sources_absent_round_trips_as_none(tmp_path: Path) -> None:
    acq = make_acquisition(sources=False)
    assert acq.sources_um is None
    write_acquisition(acq, tmp_path / "acq")
    assert "sources_um" not in json.loads((tmp_path / "acq" / "acquisition.json").read_text())
    back = read_acquisition(tmp_path / "acq")
    assert back.sources_um is None
    assert_same_acquisition(acq, back)


def test_sources_null_reads_as_none(tmp_path: Path) -> None:
    meta = base_metadata()
    meta["sources_um"] = None
    folder = write_raw_folder(tmp_path / "acq", meta, make_images())
    assert read_acquisition(folder).sources_um is None


def test_image_plane_absent_defaults_to_zero(tmp_path: Path) -> None:
    meta = base_metadata()
    del meta["image_plane_um"]
    folder = write_raw_folder(tmp_path / "acq", meta, make_images())
    acq = read_acquisition(folder)
    assert acq.optics.image_plane_um == 0.0
    assert acq.optics == Optics(0.635, 1.33, 1.0, 0.33, 14, 3.0)


def test_single_image_and_subfolder_images(tmp_path: Path) -> None:
    meta = base_metadata(1)
    meta["images"] = "raw/stack.tif"
    folder = tmp_path / "acq"
    (folder / "raw").mkdir(parents=True)
    image = make_images(1)[0]
    tifffile.imwrite(folder / "raw" / "stack.tif", image)  # a plain 2-D TIFF
    (folder / "acquisition.json").write_text(json.dumps(meta))
    acq = read_acquisition(folder)
    assert acq.images.shape == (1, 16, 12)
    np.testing.assert_array_equal(acq.images[0], image)


def test_to_metadata_and_from_metadata_inverse() -> None:
    acq = make_acquisition()
    meta = acq.to_metadata()
    assert meta["format"] == "fdt-acquisition" and meta["version"] == 1 and meta["images"] == "images.tif"
    assert meta["operator"] == "A. N. Other"
    assert_same_acquisition(acq, Acquisition.from_metadata(acq.images, meta))
    assert "sources_um" not in make_acquisition(sources=False).to_metadata("x.tif")


# --------------------------------------------------------------------------- Acquisition checks


def test_acquisition_normalises_shapes_and_dtypes() -> None:
    optics = Optics(0.635, 1.33, 1.0, 0.33, 14, 3.0)
    single = Acquisition(make_images(1)[0], optics)
    assert single.images.shape == (1, 16, 12)
    f64 = Acquisition(make_images(2, dtype=np.float64), optics)
    assert f64.images.dtype == np.float32
    u8 = Acquisition(np.full((2, 8, 8), 255, np.uint8), optics)
    assert u8.images.dtype == np.uint16 and int(u8.images.max()) == 255
    f32 = make_images(2)
    acq = Acquisition(f32, optics)
    assert acq.images_float32() is acq.images  # no copy
    assert Acquisition(make_images(2, dtype=np.uint16), optics).images_float32().dtype == np.float32
    big_endian = make_images(2).astype(">f4")
    np.testing.assert_array_equal(Acquisition(big_endian, optics).images, big_endian)


def test_negative_pixels_warn_not_raise() -> None:
    images = make_images(2)
    images[1, 3, 4] = -1.0
    with pytest.warns(FDTWarning, match="1 negative"):
        Acquisition(images, Optics(0.635, 1.33, 1.0, 0.33, 14, 3.0))


@pytest.mark.parametrize(
    "images",
    [
        np.zeros((2, 2, 16, 16), np.float32),  # 4-D
        np.zeros(16, np.float32),  # 1-D
        np.zeros((2, 16, 16), np.complex64),
        np.zeros((2, 16, 16), bool),
        np.zeros((2, 16, 16), np.int32),
        np.zeros((2, 16, 16), object),
        np.zeros((2, 7, 16), np.float32),  # too small
        np.zeros((0, 16, 16), np.float32),  # no images
        [[0.0] * 16] * 16,  # not an array
    ],
    ids=["4d", "1d", "complex", "bool", "int32", "object", "small", "empty", "list"],
)
def test_bad_image_arrays(images: Any) -> None:
    with pytest.raises(FDTInputError) as err:
        Acquisition(images, Optics(0.635, 1.33, 1.0, 0.33, 14, 3.0))
    assert err.value.field == "images"


def test_sources_checks_in_constructor() -> None:
    optics = Optics(0.635, 1.33, 1.0, 0.33, 14, 3.0)
    with pytest.raises(FDTInputError, match="2 source positions but there are 3 images") as err:
        Acquisition(make_images(3), optics, sources_um=[[0, 0, 1], [0, 0, 1]])
    assert err.value.field == "sources_um"
    with pytest.raises(FDTInputError) as err:
        Acquisition(make_images(2), optics, sources_um=np.array([[0, 0, 1], [0, 0, -1.0]]))
    assert err.value.field == "sources_um[1]" and "bottom face" in str(err.value)
    with pytest.raises(FDTInputError) as err:
        Acquisition(make_images(2), optics, sources_um=[[0, 0, 1], [0, "1", 1]])
    assert err.value.field == "sources_um[1]"
    with pytest.raises(FDTInputError) as err:
        Acquisition(make_images(2), optics, extra={"na": 0.5})
    assert err.value.field == "extra"


# --------------------------------------------------------------------------- malformed folders


def read_error(folder: Path) -> FDTInputError:
    with pytest.raises(FDTInputError) as err:
        read_acquisition(folder)
    return err.value


@pytest.mark.parametrize("key", REQUIRED_OPTICS)
def test_missing_optics_key(tmp_path: Path, key: str) -> None:
    meta = base_metadata()
    del meta[key]
    err = read_error(write_raw_folder(tmp_path / "acq", meta, make_images()))
    assert err.field == key
    assert "missing" in err.problem


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"format": "something-else"}, "format"),
        ({"format": None}, "format"),
        ({"version": 2}, "version"),
        ({"version": "1"}, "version"),
        ({"version": 1.0}, "version"),
        ({"version": 0}, "version"),
        ({"na": 1.4}, "na"),  # NA > n_background
        ({"na": 1.33}, "na"),  # NA == n_background
        ({"pixel_size_um": 0}, "pixel_size_um"),
        ({"pixel_size_um": -0.33}, "pixel_size_um"),
        ({"n_slices": 0}, "n_slices"),
        ({"n_slices": 2.5}, "n_slices"),
        ({"wavelength_um": "0.635"}, "wavelength_um"),
        ({"slice_spacing_um": math.inf}, "slice_spacing_um"),
        ({"sources_um": [[0.0, 0.0, 5.0]] * 2}, "sources_um"),  # 2 sources, 3 images
        ({"sources_um": [[0.0, 0.0, 5.0], [0.0, 0.0, 0.0], [0.0, 0.0, 5.0]]}, "sources_um[1]"),
        ({"sources_um": [[0.0, 0.0, 5.0], [0.0, 0.0, 5.0], [0.0, 0.0, -2.0]]}, "sources_um[2]"),
        ({"sources_um": [[0.0, 0.0, 5.0], [math.nan, 0.0, 5.0], [0.0, 0.0, 5.0]]}, "sources_um[1]"),
        ({"sources_um": [[0.0, 0.0, 5.0], [0.0, 0.0], [0.0, 0.0, 5.0]]}, "sources_um[1]"),
        ({"sources_um": "here"}, "sources_um"),
        ({"images": "../x.tif"}, "images"),
        ({"images": "sub/../../x.tif"}, "images"),
        ({"images": "..\\x.tif"}, "images"),
        ({"images": "/tmp/images.tif"}, "images"),
        ({"images": "C:\\data\\images.tif"}, "images"),
        ({"images": 3}, "images"),
        ({"images": ""}, "images"),
        ({"images": "missing.tif"}, "images"),
    ],
)
def test_malformed_metadata(tmp_path: Path, changes: dict[str, Any], field: str) -> None:
    meta = base_metadata()
    meta.update(changes)
    err = read_error(write_raw_folder(tmp_path / "acq", meta, make_images()))
    assert err.field == field, str(err)


def test_version_newer_says_upgrade(tmp_path: Path) -> None:
    meta = base_metadata()
    meta["version"] = 2
    err = read_error(write_raw_folder(tmp_path / "acq", meta, make_images()))
    assert "newer" in err.problem and "upgrade" in err.fix


@pytest.mark.parametrize("name", ["../x.tif", "./../x.tif", "sub/../../x.tif", "ABSOLUTE"])
def test_images_outside_folder_refused_even_if_present(tmp_path: Path, name: str) -> None:
    outside = tmp_path / "x.tif"
    # a readable stack, so only the path check can refuse it
    tifffile.imwrite(outside, make_images(), photometric="minisblack")
    meta = base_metadata()
    meta["images"] = str(outside) if name == "ABSOLUTE" else name
    folder = write_raw_folder(tmp_path / "acq", meta)
    (folder / "sub").mkdir()
    err = read_error(folder)
    assert err.field == "images"
    assert ("absolute" if name == "ABSOLUTE" else "leaves the acquisition folder") in err.problem


def test_images_file_missing_says_not_found(tmp_path: Path) -> None:
    err = read_error(write_raw_folder(tmp_path / "acq", base_metadata()))
    assert err.field == "images" and "images.tif not found" in err.problem


def test_images_key_missing(tmp_path: Path) -> None:
    meta = base_metadata()
    del meta["images"]
    assert read_error(write_raw_folder(tmp_path / "acq", meta, make_images())).field == "images"


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_pixel(tmp_path: Path, bad: float) -> None:
    images = make_images()
    images[1, 2, 3] = bad
    images[2, 0, 0] = bad
    err = read_error(write_raw_folder(tmp_path / "acq", base_metadata(), images))
    assert err.field == "images"
    assert "2 non-finite pixels" in err.problem
    assert "first at image 1, row 2, col 3" in err.problem


def test_truncated_tiff(tmp_path: Path) -> None:
    folder = write_raw_folder(tmp_path / "acq", base_metadata(), make_images(3, 32, 32))
    data = (folder / "images.tif").read_bytes()
    (folder / "images.tif").write_bytes(data[: len(data) // 2])
    err = read_error(folder)
    assert err.field == "images"
    assert "not a readable TIFF" in err.problem


def test_not_a_tiff(tmp_path: Path) -> None:
    folder = write_raw_folder(tmp_path / "acq", base_metadata())
    (folder / "images.tif").write_text("these are not pixels\n" * 10)
    err = read_error(folder)
    assert err.field == "images" and "not a readable TIFF" in err.problem


def test_images_is_a_folder(tmp_path: Path) -> None:
    folder = write_raw_folder(tmp_path / "acq", base_metadata())
    (folder / "images.tif").mkdir()
    assert read_error(folder).field == "images"


def test_four_d_tiff(tmp_path: Path) -> None:
    images = make_images(6).reshape(3, 2, 16, 12)
    assert read_error(write_raw_folder(tmp_path / "acq", base_metadata(), images)).field == "images"


def test_complex_tiff(tmp_path: Path) -> None:
    images = make_images().astype(np.complex64)
    assert read_error(write_raw_folder(tmp_path / "acq", base_metadata(), images)).field == "images"


def test_three_planes_without_photometric_read_as_stack(tmp_path: Path) -> None:
    # Older tifffile defaults store (3, H, W) as planar RGB ("SYX"); other tools may write that.
    folder = write_raw_folder(tmp_path / "acq", base_metadata())
    images = make_images()
    tifffile.imwrite(folder / "images.tif", images, photometric="rgb", planarconfig="separate")
    np.testing.assert_array_equal(read_acquisition(folder).images, images)


def test_rgb_tiff(tmp_path: Path) -> None:
    folder = write_raw_folder(tmp_path / "acq", base_metadata(1))
    tifffile.imwrite(folder / "images.tif", np.zeros((16, 16, 3), np.uint8), photometric="rgb")
    assert read_error(folder).field == "images"


def test_invalid_json(tmp_path: Path) -> None:
    bad = '{\n "format": "fdt-acquisition",\n "na": }'
    folder = write_raw_folder(tmp_path / "acq", None, make_images(), raw_json=bad)
    err = read_error(folder)
    assert err.field == "acquisition.json"
    assert "line 3, column" in err.problem


def test_json_top_level_not_object(tmp_path: Path) -> None:
    folder = write_raw_folder(tmp_path / "acq", [base_metadata()], make_images())
    err = read_error(folder)
    assert err.field == "acquisition.json" and "object" in err.problem


def test_json_duplicate_key(tmp_path: Path) -> None:
    text = json.dumps(base_metadata())[:-1] + ', "na": 0.5}'
    assert read_error(write_raw_folder(tmp_path / "acq", None, make_images(), raw_json=text)).field == "na"


def test_missing_folder_and_missing_json(tmp_path: Path) -> None:
    assert read_error(tmp_path / "nowhere").field == "path"
    (tmp_path / "empty").mkdir()
    assert read_error(tmp_path / "empty").field == "acquisition.json"
    assert read_error(tmp_path / "empty" / "acquisition.json").field == "acquisition.json"
    (tmp_path / "file.tif").write_bytes(b"x")
    assert read_error(tmp_path / "file.tif").field == "path"


def test_metadata_checked_before_pixels(tmp_path: Path) -> None:
    # A bad optics value is reported even though the TIFF is unreadable: metadata come first.
    meta = base_metadata()
    meta["na"] = 2.0
    folder = write_raw_folder(tmp_path / "a", meta)
    (folder / "images.tif").write_bytes(b"not a tiff")
    assert read_error(folder).field == "na"
    # The source count is checked from the TIFF header, before the (truncated) pixels are read.
    meta = base_metadata(2)
    folder = write_raw_folder(tmp_path / "b", meta, make_images(3, 64, 64))
    data = (folder / "images.tif").read_bytes()
    (folder / "images.tif").write_bytes(data[: len(data) // 2])
    assert read_error(folder).field == "sources_um"


def test_read_leaves_input_byte_identical(tmp_path: Path) -> None:
    folder = write_acquisition(make_acquisition(), tmp_path / "acq")
    before = folder_hashes(folder)
    mtimes = {p.name: p.stat().st_mtime_ns for p in folder.iterdir()}
    acq = read_acquisition(folder)
    with pytest.raises(ValueError, match="read-only"):  # a read-only map of the file: it cannot be changed through it
        acq.images[...] = 0
    copy = np.array(acq.images)
    copy[...] = 0
    assert folder_hashes(folder) == before
    assert {p.name: p.stat().st_mtime_ns for p in folder.iterdir()} == mtimes
    assert sorted(p.name for p in folder.iterdir()) == ["acquisition.json", "images.tif"]


# --------------------------------------------------------------------------- writer safety


def test_writer_refuses_then_overwrites(tmp_path: Path) -> None:
    dest = tmp_path / "acq"
    first = make_acquisition(seed=1)
    write_acquisition(first, dest)
    before = folder_hashes(dest)

    second = make_acquisition(n=2, dtype=np.uint16, seed=2)
    with pytest.raises(FDTInputError) as err:
        write_acquisition(second, dest)
    assert err.value.field == "path" and "exists" in err.value.problem and "overwrite" in err.value.fix
    assert folder_hashes(dest) == before
    assert hidden_siblings(tmp_path) == []

    write_acquisition(second, dest, overwrite=True)
    assert_same_acquisition(second, read_acquisition(dest))
    assert hidden_siblings(tmp_path) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["acq"]


def test_writer_refuses_to_replace_a_file(tmp_path: Path) -> None:
    (tmp_path / "acq").write_text("keep me")
    with pytest.raises(FDTInputError) as err:
        write_acquisition(make_acquisition(), tmp_path / "acq", overwrite=True)
    assert err.value.field == "path"
    assert (tmp_path / "acq").read_text() == "keep me"


def test_failed_write_leaves_old_folder_and_no_temporaries(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    dest = write_acquisition(make_acquisition(seed=1), tmp_path / "acq")
    before = folder_hashes(dest)

    def broken_imwrite(*args: Any, **kwargs: Any) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(fdt_io.tifffile, "imwrite", broken_imwrite)
    with pytest.raises(FDTInputError, match=r"^path: could not write .*disk full \(the previous one is unchanged\)"):
        write_acquisition(make_acquisition(seed=2), dest, overwrite=True)
    assert folder_hashes(dest) == before
    assert hidden_siblings(tmp_path) == []


def test_writer_creates_parents_and_rejects_bad_extra(tmp_path: Path) -> None:
    dest = write_acquisition(make_acquisition(), tmp_path / "a" / "b" / "acq")
    assert (dest / "images.tif").is_file()
    acq = make_acquisition()
    acq.extra["when"] = object()
    with pytest.raises(FDTInputError) as err:
        write_acquisition(acq, tmp_path / "other")
    assert err.value.field == "extra"
    assert not (tmp_path / "other").exists() and hidden_siblings(tmp_path) == []


def test_write_json_atomic(tmp_path: Path) -> None:
    target = tmp_path / "deep" / "er" / "result.json"
    assert write_json_atomic(target, {"a": [1, 2.5], "µ": None}) == target
    assert json.loads(target.read_text(encoding="utf-8")) == {"a": [1, 2.5], "µ": None}
    with pytest.raises(FDTInputError) as err:
        write_json_atomic(target, {"b": 1})
    assert err.value.field == "path"
    assert json.loads(target.read_text(encoding="utf-8"))["a"] == [1, 2.5]
    write_json_atomic(target, {"b": 1}, overwrite=True)
    assert json.loads(target.read_text(encoding="utf-8")) == {"b": 1}
    assert sorted(p.name for p in target.parent.iterdir()) == ["result.json"]


# --------------------------------------------------------------------------- property test

positive = st.floats(min_value=1e-3, max_value=1e3, allow_nan=False, allow_infinity=False)


@st.composite
def acquisitions(draw: st.DrawFn) -> Acquisition:
    n = draw(st.integers(1, 3))
    h = draw(st.integers(8, 12))
    w = draw(st.integers(8, 12))
    images = draw(
        hnp.arrays(np.float32, (n, h, w), elements=st.floats(width=32, allow_nan=False, allow_infinity=False))
    )
    n_background = draw(st.floats(min_value=1.0, max_value=2.5))
    na = n_background * draw(st.floats(min_value=0.01, max_value=0.99))
    optics = Optics(
        wavelength_um=draw(positive),
        n_background=n_background,
        na=na,
        pixel_size_um=draw(positive),
        n_slices=draw(st.integers(1, 512)),
        slice_spacing_um=draw(positive),
        image_plane_um=draw(st.floats(min_value=-1e3, max_value=1e3)),
    )
    sources = None
    if draw(st.booleans()):
        coord = st.floats(min_value=-1e4, max_value=1e4)
        sources = [[draw(coord), draw(coord), draw(positive)] for _ in range(n)]
    keys = st.text(min_size=1, max_size=5).map(lambda s: "x_" + s)  # never a format key
    extra = draw(st.dictionaries(keys, st.integers() | st.text(max_size=5), max_size=3))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FDTWarning)  # negative pixels
        return Acquisition(images, optics, sources_um=sources, extra=extra)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(acq=acquisitions())
def test_property_round_trip_exact(acq: Acquisition) -> None:
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore", FDTWarning)
        back = read_acquisition(write_acquisition(acq, Path(tmp) / "acq"))
    assert_same_acquisition(acq, back)
