"""``fdt reconstruct``'s half-set resolution (``half_set_resolution``, :mod:`napari_fdt.recon.run.half_sets`): estimated
after the result and its report are written, the report then written again with its ``resolution`` section."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from napari_fdt.data.io import write_json_atomic
from napari_fdt.recon.run.half_sets import describe_resolution
from napari_fdt.recon.run.session import add_resolution

__all__ = ["add_resolution_and_write"]


def add_resolution_and_write(rec, report: dict[str, Any], json_out: Path, quiet: bool) -> dict[str, Any]:
    """The half-set resolution after the result is written (``half_set_resolution``); an interrupt loses only the figure.
    Returns the report as written last."""
    print("resolution: each half of the images is reconstructed again with the run's choices (two runs on half the images)", file=sys.stderr)
    try:
        done = add_resolution(rec, report, on_half=None if quiet else lambda i: print(f"  half {i + 1}/2", file=sys.stderr))
    except KeyboardInterrupt:
        done = None
    if done is None:
        print(f"resolution not estimated (interrupted): {json_out} stands as written", file=sys.stderr)
        return report
    write_json_atomic(json_out, done, overwrite=True)
    print(describe_resolution(done["resolution"]))
    return done
