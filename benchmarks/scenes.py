"""The named scenes of the benchmarks and the tests, in one registry: where each lives and how it is made.

    python -m benchmarks run scenes list                       # every scene, its folder and whether it exists
    python -m benchmarks run scenes make NAME [NAME ...]       # simulate the missing ones (seed 0) into out/

:data:`SUITE` is the regularisation suite (docs/ablation.md); the others were made for one investigation each and are
named in its record: *cells_pupil* (issue 24: a hard pupil and pixel integration the files do not state),
*beads_high* and *cells_high* (issue 27: the suite's beads and cells made with 4 sub-slices per slice), *beads_fine* and
*cells_fine* (the same with the field on a 2× grid too: `--forward-accuracy high`), and the
model-parts scenes :data:`PARTS_SCENES` (issue 13, docs/decisions/model-parts.md; out/parts/): the sample's geometry
(``letters``) and 64² beads, each ``_clean``, with real-optics ``_effects`` (pixel integration, a hard pupil and
0.5 rad of spherical aberration; the first two stated in acquisition.json) and ``_real`` (the ``_effects`` images
with those statements removed, as a microscope's files would be).

:func:`tiny_scene` is the tests' scene (32×32 px, 4 slices, seconds to reconstruct), made in memory.
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENE_DIR = ROOT / "out" / "scenes"

#: name → (folder, the `fdt simulate` arguments before the folder; None: a folder that is not simulated)
SUITE: dict[str, tuple[Path, str | None]] = {
    "sample": (ROOT / "sample_data" / "letters", None),
    "letters128": (SCENE_DIR / "letters128", "letters --shape 128 128 --n-slices 10 --slice-spacing-um 1.5 --wavelength-um 0.6 "
                                             "--na 0.65 --sources 14 --span-um 60 --depth-um 50 --delta-n 0.03"),
    "beads": (SCENE_DIR / "beads", "beads --shape 64 64 --n-slices 8 --sources 7 --depth-um 30"),
    "cells": (SCENE_DIR / "cells", "cells --shape 64 64 --n-slices 8 --sources 7 --depth-um 30"),
    "deep": (SCENE_DIR / "deep", "letters --shape 64 64 --n-slices 8 --na 0.5 --pixel-size-um 0.5 --sources 7 --depth-um 120 "
                                 "--image-plane-um 8 --delta-n 0.03"),
    # the authors' demo geometry as benchmarks/suite.py builds it (GPU only: 1521 images of 512²)
    "demo": (SCENE_DIR / "demo", "letters --shape 512 512 --n-slices 14 --slice-spacing-um 1.5 --wavelength-um 0.6 --na 0.65 "
                                 "--image-plane-um 10.5 --sources 39 --span-um 84 --depth-um 50 --delta-n 0.03 --letter-height-px 100"),
}

#: every named scene
SCENES: dict[str, tuple[Path, str | None]] = {
    **SUITE,
    "cells_pupil": (SCENE_DIR / "cells_pupil", "cells --shape 96 96 --n-slices 6 --sources 11 --depth-um 25 --pupil-edge 0 "
                                               "--pixel-integration true"),
    "beads_high": (SCENE_DIR / "beads_high", "beads --shape 64 64 --n-slices 8 --sources 7 --depth-um 30 --sub-slices 4"),
    "cells_high": (SCENE_DIR / "cells_high", "cells --shape 64 64 --n-slices 8 --sources 7 --depth-um 30 --sub-slices 4"),
    # the same with every accuracy part of the simulator: 4 sub-slices and the field on a 2x grid (issue 27)
    "beads_fine": (SCENE_DIR / "beads_fine", "beads --shape 64 64 --n-slices 8 --sources 7 --depth-um 30 --forward-accuracy high"),
    "cells_fine": (SCENE_DIR / "cells_fine", "cells --shape 64 64 --n-slices 8 --sources 7 --depth-um 30 --forward-accuracy high"),
    # a thick slab of elongated objects (issue 47): 3 µm slices, the focus inside the volume, the accurate forward model
    "fibres_thick": (SCENE_DIR / "fibres_thick", "fibres --shape 64 64 --n-slices 8 --slice-spacing-um 3 --image-plane-um 12 "
                                                 "--sources 7 --depth-um 30 --forward-accuracy high"),
    # data that do carry an emission band (40 nm FWHM, 9 wavelengths; issue 49): the spectral model belongs to them
    "beads_spectral": (SCENE_DIR / "beads_spectral", "beads --shape 64 64 --n-slices 8 --sources 7 --depth-um 30 --bandwidth-um 0.04"),
    "cells_spectral": (SCENE_DIR / "cells_spectral", "cells --shape 64 64 --n-slices 8 --sources 7 --depth-um 30 --bandwidth-um 0.04 "
                                                     "--forward-accuracy high"),
}

#: the model-parts scenes (benchmarks/model_parts.py): the sample's geometry and 64² beads, clean and with the
#: real-optics effects; ``_real`` is made from ``_effects`` (:data:`COPIES`)
PARTS_DIR = ROOT / "out" / "parts"
EFFECTS = "--pixel-integration true --pupil-edge 0 --aberrations spherical=0.5"
_PARTS_BASE = {"letters": "letters --seed 0", "beads": "beads --shape 64 64 --n-slices 8 --sources 7 --depth-um 30 --seed 0"}
PARTS_SCENES: dict[str, tuple[Path, str | None]] = {
    f"{base}_{version}": (PARTS_DIR / f"{base}_{version}", args + ("" if version == "clean" else " " + EFFECTS))
    for base, args in _PARTS_BASE.items() for version in ("clean", "effects", "real")
}
SCENES.update(PARTS_SCENES)

#: scenes made by copying another scene's folder (the same images) before the keys of :data:`UNSTATED` are removed
COPIES: dict[str, str] = {f"{base}_real": f"{base}_effects" for base in _PARTS_BASE}

#: keys removed from acquisition.json after simulating, so that the solver does not know them (a real microscope's
#: files would not state them)
UNSTATED: dict[str, tuple[str, ...]] = {"cells_pupil": ("pupil_edge",),
                                        **{name: ("pixel_integration", "pupil_edge", "simulated") for name in COPIES}}


def folder_of(name: str) -> Path:
    """The folder of a named scene, or ``out/scenes/NAME`` for a name the registry does not hold."""
    return SCENES[name][0] if name in SCENES else SCENE_DIR / name


def make_scenes(names: list[str], device: str = "cpu") -> None:
    """Simulate the named scenes with ``fdt simulate`` (seed 0) where they are missing."""
    for name in names:
        folder, args = SCENES[name]
        if args is None or (folder / "acquisition.json").is_file():
            continue
        if name in COPIES:
            make_scenes([COPIES[name]], device)
            shutil.copytree(SCENES[COPIES[name]][0], folder)
        else:
            cmd = [sys.executable, "-m", "napari_fdt", "simulate", *shlex.split(args), str(folder), "--device", device]
            print(" ".join(cmd[2:]), flush=True)
            subprocess.run(cmd, check=True)
        drop = UNSTATED.get(name, ())
        if drop:
            meta_path = folder / "acquisition.json"
            meta = json.loads(meta_path.read_text())
            meta_path.write_text(json.dumps({k: v for k, v in meta.items() if k not in drop}, indent=1))


def tiny_optics():
    """The tests' optics: λ 0.635 µm, n_b 1.33, NA 0.8, 0.33 µm pixels, 4 slices of 2 µm, the camera at the top face."""
    from napari_fdt import Optics

    return Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=4, slice_spacing_um=2.0)


def tiny_scene(grid: int = 3, seed: int = 1, **simulate_options):
    """The tests' scene, in memory: the letters "UC" (Δn 0.05) on 32×32 px and 4 slices (:func:`tiny_optics`),
    ``grid``² sources 8 µm apart 15 µm below the volume; ``seed`` the noise's; more :func:`napari_fdt.simulate` options
    (``noise``, ``photons``, ...) as keywords. Returns its :class:`~napari_fdt.sim.simulate.Simulation`."""
    from napari_fdt import simulate, source_grid
    from napari_fdt.sim.phantoms import text_phantom

    return simulate(text_phantom((32, 32), 4, text="UC", delta_n=0.05), tiny_optics(), source_grid(grid, 8.0, 15.0),
                    seed=seed, device="cpu", **simulate_options)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("list")
    m = sub.add_parser("make")
    m.add_argument("names", nargs="+")
    m.add_argument("--device", default="cpu")
    args = ap.parse_args()
    if args.cmd == "list":
        for name, (folder, recipe) in SCENES.items():
            state = "present" if (folder / "acquisition.json").is_file() else "missing"
            if name in COPIES:
                recipe = f"a copy of {COPIES[name]} without {', '.join(UNSTATED[name])} in acquisition.json"
            print(f"{name:<15} {state:<8} {folder.relative_to(ROOT)}  {recipe or '(bundled)'}")
        return
    make_scenes(args.names, args.device)


if __name__ == "__main__":
    main()
