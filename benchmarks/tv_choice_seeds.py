"""The automatic TV weight for several batch-order seeds: the run up to its choice (no full run), each weight's held-out error.

Usage (repository root; a scene folder of ``benchmarks/model_parts.py``)::

    python -m benchmarks run tv_choice_seeds out/parts/letters_clean 0 1 2

Used in docs/decisions/run-to-run-spread.md to tell a spread of the chosen weight from a spread of the trajectory.
"""

from __future__ import annotations

import sys

import torch

from napari_fdt import read_acquisition
from napari_fdt.recon.config import SolverConfig
from napari_fdt.recon.solver import Reconstructor


def main(argv: list[str]) -> None:
    torch.set_num_threads(1)
    acq = read_acquisition(argv[0])
    for seed in map(int, argv[1:]):
        rec = Reconstructor(acq, SolverConfig(seed=seed), device="cpu")
        run = rec.run()
        for _ in run:  # up to the choice: the first snapshot after it
            if rec.tv_choice is not None:
                break
        run.close()
        c = rec.tv_choice
        trials = ", ".join(f"τ {t['tau']:g}: {t['validation_error']:.5f}" for t in c.trials)
        print(f"{argv[0]} seed {seed}: τ_xy {c.tv_xy_weight:g} ({trials})", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
