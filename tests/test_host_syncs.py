"""The solver's iteration leaves the GPU's queue alone: no host wait with the sources' step in its CUDA form; on the
CPU (where a wait costs nothing) at most the two of the rows' own form.

On CUDA every operation whose result the host must read (a Python number from a tensor, a boolean-mask index, a
``nonzero``, ``linalg.eigh``'s status check) stops the host from queueing the next kernels. They are counted here on
the CPU with the operators the GPU would run (``benchmarks/host_syncs.py``); before 2026-11-26 an iteration of the
sample's finest stage made 17.7 of them (the batch split on the device, the sources' row selection by boolean masks).
"""

from __future__ import annotations

from pathlib import Path

from benchmarks.host_syncs import count_syncs, finest_step
from napari_fdt import read_acquisition

SAMPLE = Path(__file__).resolve().parents[1] / "sample_data" / "letters"


def test_the_finest_iteration_waits_for_the_device_at_most_twice() -> None:
    steps = 3
    counter = count_syncs(finest_step(read_acquisition(SAMPLE), "full"), steps)
    sites = {site for (_, site) in counter.sites}
    assert counter.total <= 2 * steps, counter.sites
    # the two left: the rows of the sources that have a gradient (one nonzero) and eigh's status (whitened steps)
    assert all("recon/calibration/calibration.py" in site for site in sites), counter.sites
    assert counter.total > 0  # the counter sees the operators at all (it would pass vacuously otherwise)


def test_the_finest_iteration_in_the_gpus_form_never_waits_for_the_device(monkeypatch) -> None:
    """On CUDA the sources' step takes every row with the unvisited masked out and the whitening by Newton–Schulz
    (``RowAdam._masked_step``): forced here on the CPU, the iteration has no operator that waits."""
    from napari_fdt.recon.calibration.calibration import RowAdam

    monkeypatch.setattr(RowAdam, "sync_free", True)
    steps = 3
    counter = count_syncs(finest_step(read_acquisition(SAMPLE), "full"), steps)
    assert counter.total == 0, counter.sites
    monkeypatch.setattr(RowAdam, "sync_free", False)  # and the counter does see the rows' form's two
    assert count_syncs(finest_step(read_acquisition(SAMPLE), "full"), steps).total > 0


def test_the_counter_sees_a_boolean_index_and_a_python_number() -> None:
    import torch

    x = torch.arange(6.0)

    def step() -> None:
        _ = x[x > 2]
        _ = float(x.sum())

    counter = count_syncs(step, 2)
    assert sorted(name for (name, _) in counter.sites) == ["_local_scalar_dense", "index"]
    assert counter.total == 4
