"""A checkpoint from elsewhere cannot run code (issue 51): checkpoints hold plain data and tensors and are read with
``torch.load(weights_only=True)``; a pickle of anything else is refused before any of it is built, with exit status 2."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch

from napari_fdt.cli import main
from napari_fdt.data.io import write_acquisition
from napari_fdt.errors import FDTInputError
from napari_fdt.recon.loop.checkpoint import FORMAT, VERSION, _from_plain, _plain, read_checkpoint
from napari_fdt.recon.run.solver import Reconstructor
from napari_fdt.recon.settings.config import SolverConfig, StageConfig


class _Payload:
    """What a crafted checkpoint holds: unpickling it runs ``touch MARKER``."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch '{self.marker}'",))


def crafted_checkpoint(path: Path, marker: Path) -> Path:
    """The issue's file: a pickle whose loading would create ``marker``."""
    torch.save({"format": _Payload(marker)}, path)
    return path


def test_the_payload_runs_code_when_unpickled_the_unsafe_way(tmp_path: Path) -> None:
    """The control: the crafted file does run code through a plain unpickler (what read_checkpoint did before)."""
    marker = tmp_path / "code_ran"
    torch.load(crafted_checkpoint(tmp_path / "stage_0.pt", marker), weights_only=False)
    assert marker.exists()


def test_a_crafted_checkpoint_is_refused_by_the_cli_and_runs_no_code(tmp_path: Path, tiny_sim, capsys) -> None:
    acq = write_acquisition(tiny_sim.acquisition, tmp_path / "acq")
    marker = tmp_path / "code_ran"
    for resume in (crafted_checkpoint(tmp_path / "stage_0.pt", marker), tmp_path):  # the file, or its folder
        code = main(["reconstruct", str(acq), "--out", str(tmp_path / "RI.tif"), "--resume", str(resume), "--device", "cpu", "--quiet"])
        err = capsys.readouterr().err
        assert code == 2
        assert not marker.exists()
        assert "error: resume:" in err and "no code in it ran" in err and "without --resume" in err
        assert not (tmp_path / "RI.tif").exists()


def test_a_version_1_checkpoint_is_refused_with_the_fix(tmp_path: Path, tiny_sim) -> None:
    """Version 1 pickled a NumPy array (the initial sources): it cannot be read safely, and says what to do."""
    path = tmp_path / "stage_0.pt"
    torch.save({"format": FORMAT, "version": 1, "initial_sources_um": np.zeros((9, 3))}, path)
    with pytest.raises(FDTInputError) as exc:
        read_checkpoint(path, tiny_sim.acquisition)
    assert exc.value.field == "resume" and "version-1" in str(exc.value) and "without --resume" in str(exc.value)
    torch.save({"format": FORMAT, "version": 1, "n_images": 9}, path)  # plain data, but an older layout
    with pytest.raises(FDTInputError, match="version-1 checkpoint; this napari-fdt reads version 2"):
        read_checkpoint(path, tiny_sim.acquisition)


def test_plain_data_round_trips_and_anything_else_is_a_bug() -> None:
    state = {"a": np.arange(6, dtype=np.float64).reshape(2, 3), "b": [np.float32(1.5), np.bool_(True), (1, "x")],
             "t": torch.ones(2), "n": None}
    plain = _plain(state)
    back = _from_plain(plain)
    assert isinstance(back["a"], np.ndarray) and back["a"].dtype == np.float64 and np.array_equal(back["a"], state["a"])
    assert back["b"] == [1.5, True, (1, "x")] and type(back["b"][0]) is float and type(back["b"][1]) is bool
    with pytest.raises(TypeError, match=r"checkpoint\.x is a .*SolverConfig"):
        _plain({"x": SolverConfig()})


def test_every_checkpoint_a_run_writes_is_plain_data_and_resumes_exactly(tmp_path: Path, scene16) -> None:
    """A run with the TV weights and the model parts chosen by the data, held-out images, early stopping and checkpoints
    inside the stages: each file loads with ``weights_only=True`` and no allow-list; resumed from the last in-stage
    checkpoint, the run ends where the uninterrupted one did."""
    cfg = SolverConfig(stages=[StageConfig(2, 6), StageConfig(1, 8)], batch_size=4, snapshot_every=2, checkpoint_every_s=0.0,
                       final_stage_min_passes=0)
    folder = tmp_path / "ck"
    full = Reconstructor(scene16.acquisition, cfg, device="cpu")
    seen: set[str] = set()
    for _ in full.run(checkpoint_dir=folder):
        for p in folder.glob("stage_*.pt"):
            if p.name not in seen:
                seen.add(p.name)
                state = torch.load(p, weights_only=True)  # no allow-list: plain data and tensors only
                assert state["format"] == FORMAT and state["version"] == VERSION
                if "_it" in p.name:
                    (tmp_path / "inside.pt").write_bytes(p.read_bytes())
    assert any("_it" in n for n in seen) and "stage_1.pt" in seen and (tmp_path / "inside.pt").exists()
    assert full.tv_choice is not None and full.parts_choice is not None
    resumed = Reconstructor.from_checkpoint(tmp_path / "inside.pt", scene16.acquisition, device="cpu")
    for _ in resumed.run():
        pass
    assert np.abs(resumed.delta_n_full() - full.delta_n_full()).max() <= 1e-6
    assert np.abs(resumed.sources_um() - full.sources_um()).max() <= 1e-5


def _ome_zarr_attrs() -> dict:
    return {"multiscales": [{"version": "0.4", "axes": [{"name": a, "type": "space", "unit": "micrometer"} for a in "zyx"],
                             "datasets": [{"path": "0", "coordinateTransformations": [{"type": "scale", "scale": [1, 1, 1]}]}]}]}


@pytest.mark.parametrize("dtype", ["|O", "<f4"])
def test_an_ome_zarr_array_with_a_pickle_codec_is_refused_before_zarr_reads_it(tmp_path: Path, dtype: str) -> None:
    """zarr 2 (our Python 3.10 path) decodes a chunk through numcodecs' Pickle filter, which would run code: the array's
    JSON is checked first, for numbers and for codecs that only decompress or filter numbers."""
    import json

    from napari_fdt.data.ome_zarr import read_volume_zarr

    root = tmp_path / "evil.ome.zarr"
    (root / "0").mkdir(parents=True)
    (root / ".zattrs").write_text(json.dumps(_ome_zarr_attrs()))
    (root / ".zgroup").write_text('{"zarr_format": 2}')
    (root / "0" / ".zarray").write_text(json.dumps({
        "zarr_format": 2, "shape": [1, 1, 1], "chunks": [1, 1, 1], "dtype": dtype, "compressor": None, "fill_value": None,
        "order": "C", "filters": [{"id": "pickle", "protocol": 4}], "dimension_separator": "."}))
    marker = tmp_path / "code_ran"
    import pickle
    (root / "0" / "0.0.0").write_bytes(pickle.dumps(_Payload(marker)))
    with pytest.raises(FDTInputError, match="not numbers" if dtype == "|O" else "codec.*pickle"):
        read_volume_zarr(root)
    assert not marker.exists()


def test_ome_zarr_arrays_of_both_formats_with_standard_codecs_are_read(tmp_path: Path) -> None:
    import json

    import zarr

    from napari_fdt.data.ome_zarr import read_volume_zarr, write_volume_zarr

    vol = np.full((2, 4, 4), 1.34, np.float32)
    write_volume_zarr(tmp_path / "v2.ome.zarr", vol, (1.0, 0.5, 0.5))
    assert np.array_equal(read_volume_zarr(tmp_path / "v2.ome.zarr")[0], vol)
    if int(zarr.__version__.split(".")[0]) >= 3:  # format 3: codecs bytes + zstd, in a sharded array too
        for shards in (None, (2, 4, 4)):
            root = zarr.open_group(str(tmp_path / f"v3{shards is None}.ome.zarr"), mode="w", zarr_format=3)
            arr = root.create_array("0", shape=vol.shape, chunks=(1, 4, 4), shards=shards, dtype="float32")
            arr[...] = vol
            root.attrs.update({"ome": {"version": "0.5", **_ome_zarr_attrs()}})
            assert json.loads((tmp_path / f"v3{shards is None}.ome.zarr" / "0" / "zarr.json").read_text())["codecs"]
            assert np.array_equal(read_volume_zarr(tmp_path / f"v3{shards is None}.ome.zarr")[0], vol)
