"""The ``fdt`` command line's argument parser: one subcommand per job, the solver's and the optics' settings as typed
flags generated from their settings classes (``--tv-xy-weight``; booleans as ``--x/--no-x``)."""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["build_parser"]


def _schema_help(info, default) -> str:
    """``--help`` text of a schema field: its description, bounds and default (``%`` escaped for argparse)."""
    from napari_fdt.schema import bounds

    signs = {"ge": ">=", "gt": ">", "le": "<=", "lt": "<"}
    limits = ", ".join(f"{signs[k]} {v:g}" for k, v in bounds(info).items())
    text = (info.description or "").replace("`", "") + (f"; {limits}" if limits else "") + ("" if default is None else f" (default {default})")
    return text.replace("%", "%%")


def _number_or_words(kind: type, words: tuple[str, ...]):
    """An argparse type for a number that may also be one of ``words`` (``auto``)."""
    def parse(text: str):
        word = text.strip().lower()
        return word if word in words else kind(text)
    parse.__name__ = " or ".join((kind.__name__,) + words)
    return parse


def _add_schema_args(group, model, defaults: dict | None = None, tiers: tuple[str, ...] | None = None) -> None:
    """One flag per scalar field of a settings class (``--tv-xy-weight``; booleans as ``--x/--no-x``), typed,
    with the ``Literal`` choices and the description as help. With ``defaults`` None every flag defaults to
    None (unset: it overrides nothing); else the flag's default is ``defaults[name]``. ``tiers``: only the fields of
    these tiers (:data:`napari_fdt.schema.TIERS`; None: all)."""
    from napari_fdt.schema import choices, number_words, scalar_type, schema_fields, tier

    for name, info in schema_fields(model).items():
        kind, _ = scalar_type(info)
        if kind is None or (tiers is not None and tier(info) not in tiers):
            continue
        default = None if defaults is None else defaults[name]
        shown = info.get_default(call_default_factory=True) if defaults is None else default
        kwargs = dict(dest=name, default=default, help=_schema_help(info, shown))
        if kind is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
        else:
            kwargs["type"] = _number_or_words(kind, number_words(info)) if number_words(info) else kind
            if choices(info) is not None:
                kwargs["choices"] = choices(info)
            if tuple(choices(info) or ()) == ("auto", "true", "false"):  # a switch: the flag alone means "true"
                kwargs.update(nargs="?", const="true")
        group.add_argument("--" + name.replace("_", "-"), **kwargs)


def _add_optics_args(p: argparse.ArgumentParser) -> None:
    from napari_fdt.physics.optics import Optics

    g = p.add_argument_group("optics and sampling (µm)")
    g.add_argument("--shape", type=int, nargs=2, default=(96, 96), metavar=("H", "W"), help="image size in pixels (default 96 96)")
    _add_schema_args(g, Optics, defaults=Optics.examples())


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``fdt``."""
    from napari_fdt.recon.settings.config import SolverConfig

    parser = argparse.ArgumentParser(prog="fdt", description="Fluorescence diffraction tomography (napari-fdt).")
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command")

    sim = sub.add_parser("simulate", help="simulate an acquisition folder with its ground truth")
    sim.add_argument("scene", choices=("letters", "beads", "cells", "fibres"), help="test scene")
    sim.add_argument("out_dir", type=Path, help="acquisition folder to create")
    _add_optics_args(sim)
    s = sim.add_argument_group("sources")
    s.add_argument("--sources", type=int, default=8, help="sources per side of the square grid (default 8: 64 images)")
    s.add_argument("--span-um", type=float, default=None, help="lateral extent of the source grid, µm (default 80%% of the field of view)")
    s.add_argument("--depth-um", type=float, default=40.0, help="source depth below the volume's bottom face, µm (default 40)")
    s.add_argument("--jitter-um", type=float, default=1.0, help="RMS error per axis of the initial source estimates, µm (default 1)")
    m = sim.add_argument_group("measurement")
    m.add_argument("--photons", type=float, default=2000.0, help="mean photo-electrons per pixel (default 2000)")
    m.add_argument("--read-noise", type=float, default=2.0, help="camera read noise, electrons RMS (default 2)")
    m.add_argument("--brightness-spread", type=float, default=0.2, help="log-normal spread of source brightness (default 0.2)")
    m.add_argument("--no-noise", action="store_true", help="write the expected images without noise")
    m.add_argument("--uint16", action="store_true", help="write images as uint16 counts instead of float32")
    m.add_argument("--bandwidth-um", type=float, default=0.0,
                   help="FWHM of the Gaussian emission spectrum, µm (default 0: coherent); e.g. 0.04 for 40 nm: "
                        "fringes beyond the coherence length λ²/(n_b·FWHM) wash out")
    m.add_argument("--n-wavelengths", type=int, default=9,
                   help="wavelengths sampling the emission spectrum when --bandwidth-um > 0 (default 9; costs that many forward passes)")
    m.add_argument("--pixel-integration", choices=("auto", "true", "false"), default="false",
                   help="average the intensity over each camera pixel (auto: when 2·NA/λ > 1/(2·pixel); default false)")
    m.add_argument("--pupil-edge", type=float, default=None,
                   help="half-width of the pupil's soft edge relative to NA/λ (default 0.03; 0: a hard pupil)")
    m.add_argument("--sub-slices", type=int, default=None,
                   help="screens per slice: each slice crossed in this many symmetric steps, so that diffraction inside "
                        "thick slices is modelled (default 1; --forward-accuracy high: 4)")
    m.add_argument("--field-oversampling", type=int, choices=(1, 2), default=None,
                   help="2: the field on a grid twice as fine as the camera's, so that light scattered beyond the camera "
                        "grid's Nyquist is propagated, not aliased (about 4x the cost; default 1; --forward-accuracy high: 2)")
    m.add_argument("--forward-accuracy", choices=("standard", "high"), default="standard",
                   help="high: every accuracy part of the forward model on (4 sub-slices per slice, a field grid twice as "
                        "fine), for data the solver's model cannot fit exactly (docs/physics.md, \"Sub-slices\", "
                        "\"A finer field grid\")")
    m.add_argument("--aberrations", default=None,
                   help="pupil phase, Zernike modes in radians (Noll RMS), e.g. spherical=0.5,defocus=-0.2; modes: defocus, "
                        "astigmatism_oblique, astigmatism_vertical, coma_vertical, coma_horizontal, spherical")
    sc = sim.add_argument_group("scene")
    sc.add_argument("--delta-n", type=float, default=None, help="index contrast of the objects (scene default)")
    sc.add_argument("--text", default="UCDAVIS", help="letters of the letters scene (A-Z, 0-9)")
    sc.add_argument("--letter-height-px", type=int, default=None, help="letter height in pixels (default 40%% of the image)")
    sim.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sim.add_argument("--device", default="auto", help="auto, cpu or cuda (default auto)")
    sim.add_argument("--overwrite", action="store_true", help="replace an existing output folder")

    info = sub.add_parser("info", help="check an acquisition folder and show the forward model's grid")
    info.add_argument("acquisition", type=Path)

    rec = sub.add_parser("reconstruct", help="reconstruct the RI volume of an acquisition")
    rec.add_argument("acquisition", type=Path, nargs="?", default=None,
                     help="acquisition folder (may be left out with --config REPORT: the report's acquisition is used)")
    rec.add_argument("--out", type=Path, required=True,
                     help="RI volume to write: OME-TIFF (.tif, .ome.tif) or OME-Zarr (.ome.zarr); the report goes beside it, "
                          "named from the full name (RI_lr0.05.tif → RI_lr0.05.json)")
    rec.add_argument("--config", type=Path, default=None,
                     help="solver settings: a settings file (JSON/TOML, docs/solver.md) or a report RI.json written by fdt or "
                          "napari-fdt, whose settings (seed included) are rerun")
    rec.add_argument("--device", default="auto", help="auto, cpu or cuda (default auto)")
    rec.add_argument("--truth", type=Path, default=None,
                     help="ground-truth RI TIFF for metrics (ground_truth_sources_um.json beside it is used too)")
    rec.add_argument("--checkpoint-dir", type=Path, default=None, help="write a checkpoint at the end of every stage here")
    rec.add_argument("--resume", type=Path, default=None, help="continue from a checkpoint written by --checkpoint-dir: its "
                     "folder (the checkpoint written last; a family's folder resumes the family) or one stage_*.pt file")
    rec.add_argument("--overwrite", action="store_true", help="replace existing output files")
    rec.add_argument("--quiet", action="store_true", help="no progress bar (the plan is still printed at the start)")
    rec.add_argument("--save-config", type=Path, default=None, help="write the full configuration used to this file and exit")
    rec.add_argument("--dist-backend", choices=("auto", "nccl", "gloo"), default="auto",
                     help="under torchrun: the torch.distributed backend (default auto: NCCL when each rank has a GPU "
                          "of its own, else gloo; env FDT_DIST_BACKEND); docs/distributed.md")
    for tier_name, title in (("basic", "solver settings (docs/solver.md; each overrides the --config file's value)"),
                             ("advanced", "advanced solver settings"),
                             ("experimental", "experimental solver settings (kept while they are measured: docs/solver.md)")):
        _add_schema_args(rec.add_argument_group(title), SolverConfig, tiers=(tier_name,))

    pl = sub.add_parser("plan", help="what a reconstruction would do: its phases, predicted seconds and peak memory, "
                                     "before any long computation")
    pl.add_argument("acquisition", type=Path)
    pl.add_argument("--config", type=Path, default=None, help="solver settings, as fdt reconstruct --config reads them")
    pl.add_argument("--device", default="auto", help="auto, cpu or cuda (default auto): the device the prediction is for")
    pl.add_argument("--json", action="store_true", help="print one JSON object (phases, predicted_total_s, peak_memory_bytes)")
    _add_schema_args(pl.add_argument_group("solver settings (each overrides the --config file's value)"), SolverConfig,
                     tiers=("basic",))

    fwd = sub.add_parser("forward", help="predict an acquisition's images from an RI volume and report the residual")
    fwd.add_argument("acquisition", type=Path)
    fwd.add_argument("--ri", type=Path, required=True, help="RI volume TIFF, absolute index, (n_slices, H, W)")
    fwd.add_argument("--out", type=Path, default=None, help="write the predicted images here (TIFF)")
    fwd.add_argument("--device", default="auto", help="auto, cpu or cuda (default auto)")
    fwd.add_argument("--batch-size", type=int, default=16, help="images per forward batch (default 16)")
    fwd.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    return parser
