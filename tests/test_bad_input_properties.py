"""Property-based bad input: whatever a user writes, the error is an FDTInputError naming a field, never a crash."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import tifffile
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from napari_fdt.config import SolverConfig
from napari_fdt.errors import FDTInputError
from napari_fdt.io import read_acquisition

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
