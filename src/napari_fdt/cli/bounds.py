"""``fdt reconstruct --error-bounds``: the per-voxel error bound (:mod:`napari_fdt.recon.run.error_bounds`) made after
the result and its report are written, then written beside the result (``RI.tif`` → ``RI_bounds.tif``, Δn units, the
same grid) and the report written again with its ``error_bounds`` section. An interrupt loses only the bound."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from napari_fdt.data.io import beside, write_json_atomic
from napari_fdt.data.volumes import write_volume
from napari_fdt.errors import FDTInputError
from napari_fdt.recon.run.error_bounds import REPLICATES, error_bounds

__all__ = ["bounds_path", "check_bounds_request", "add_bounds_and_write", "describe_error_bounds"]


def bounds_path(out: Path) -> Path:
    """Where the bound of ``out`` goes: ``RI.tif`` → ``RI_bounds.tif`` (``RI.ome.zarr`` → ``RI_bounds.ome.zarr``)."""
    return beside(out, "bounds")


def check_bounds_request(config, out: Path, protected: set[Path], world_size: int) -> Path:
    """Refuse, before the run, a bound that would overwrite an input, one asked with a TV family, or one under torchrun
    (``world_size`` > 1: the bound is made in one process); returns where the bound will go."""
    bound_out = bounds_path(out)
    if bound_out.resolve() in protected:
        raise FDTInputError("out", f"the error bound {bound_out} would overwrite an input", "write the result somewhere else")
    if config.tv_family == "true":
        raise FDTInputError("error_bounds", "and tv_family together are not built: the bound is made for one run",
                            "drop --tv-family, or make the bound of the member you pick with --config its RI.json")
    if world_size > 1:
        raise FDTInputError("error_bounds", "is made in one process: a data-parallel run (torchrun) would skip it",
                            "drop --error-bounds here, then make the bound in one process: fdt reconstruct ACQ --config "
                            "RI.json --error-bounds (the result's settings, run again)")
    return bound_out


def describe_error_bounds(section: dict[str, Any]) -> str:
    """One line for people from the report's ``error_bounds`` section."""
    return (f"error bound: {section['path']} (|Δn − Δn_true| ≤ bound on about {100 * section['level']:.0f} % of the voxels "
            f"of the calibration's simulated scenes; mean {section['mean_bound']:.2e}, max {section['max_bound']:.2e} RI; "
            f"{section['replicates']} re-simulated runs, {section['seconds']:.0f} s). Structure whose |Δn| is below the "
            "bound may not be real (docs/guide.md, \"Can I believe this structure?\")")


def add_bounds_and_write(rec, report: dict[str, Any], out: Path, json_out: Path, quiet: bool, overwrite: bool) -> dict[str, Any]:
    """The bound after the result is written (``error_bounds``); returns the report as written last."""
    print(f"error bound: the result is re-simulated and reconstructed again with the run's choices ({REPLICATES} runs)",
          file=sys.stderr)
    try:
        made = error_bounds(rec, on_replicate=None if quiet else lambda k: print(f"  replicate {k + 1}/{REPLICATES}", file=sys.stderr))
    except KeyboardInterrupt:
        made = None
    if made is None:
        print(f"error bound not made (interrupted): {json_out} stands as written", file=sys.stderr)
        return report
    o = rec.acquisition.optics
    path = write_volume(bounds_path(out), made.bound, (o.slice_spacing_um, o.pixel_size_um, o.pixel_size_um), overwrite=overwrite)
    report = {**report, "error_bounds": made.to_dict(path=str(path))}
    write_json_atomic(json_out, report, overwrite=True)
    print(describe_error_bounds(report["error_bounds"]))
    return report
