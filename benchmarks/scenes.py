"""The named scenes of the benchmarks, in one registry: where each lives and the `fdt simulate` line that makes it.

    python -m benchmarks run scenes list                       # every scene, its folder and whether it exists
    python -m benchmarks run scenes make NAME [NAME ...]       # simulate the missing ones (seed 0) into out/scenes/

:data:`SUITE` is the regularisation suite (docs/ablation.md); the others were made for one investigation each and are
named in its record: *cells_pupil* (issue 24: a hard pupil and pixel integration the files do not state),
*beads_high* and *cells_high* (issue 27: the suite's beads and cells made with 4 sub-slices per slice). The model-parts
scenes (`benchmarks/model_parts.py`, out/parts/) are built in Python with their aberrations and stay there.
"""

from __future__ import annotations

import argparse
import json
import shlex
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
    "beads_high": (SCENE_DIR / "beads_high", "beads --shape 64 64 --n-slices 8 --sources 7 --depth-um 30 --forward-accuracy high"),
    "cells_high": (SCENE_DIR / "cells_high", "cells --shape 64 64 --n-slices 8 --sources 7 --depth-um 30 --forward-accuracy high"),
}

#: keys removed from acquisition.json after simulating, so that the solver does not know them (a real microscope's
#: files would not state them)
UNSTATED: dict[str, tuple[str, ...]] = {"cells_pupil": ("pupil_edge",)}


def folder_of(name: str) -> Path:
    """The folder of a named scene, or ``out/scenes/NAME`` for a name the registry does not hold."""
    return SCENES[name][0] if name in SCENES else SCENE_DIR / name


def make_scenes(names: list[str], device: str = "cpu") -> None:
    """Simulate the named scenes with ``fdt simulate`` (seed 0) where they are missing."""
    for name in names:
        folder, args = SCENES[name]
        if args is None or (folder / "acquisition.json").is_file():
            continue
        cmd = [sys.executable, "-m", "napari_fdt", "simulate", *shlex.split(args), str(folder), "--device", device]
        print(" ".join(cmd[2:]), flush=True)
        subprocess.run(cmd, check=True)
        drop = UNSTATED.get(name, ())
        if drop:
            meta_path = folder / "acquisition.json"
            meta = json.loads(meta_path.read_text())
            meta_path.write_text(json.dumps({k: v for k, v in meta.items() if k not in drop}, indent=1))


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
            print(f"{name:<12} {state:<8} {folder.relative_to(ROOT)}  {recipe or '(bundled)'}")
        return
    make_scenes(args.names, args.device)


if __name__ == "__main__":
    main()
