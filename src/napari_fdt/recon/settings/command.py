"""Hand a run to the command line: the ``fdt reconstruct`` line that reproduces it, and settings read back from a report.

* :func:`reconstruct_command` builds the argument list of ``fdt reconstruct`` from an acquisition folder, an
  output path, the settings (a :class:`~napari_fdt.recon.settings.config.SolverConfig`, a settings file or a report
  ``RI.json``), the seed and the device; :func:`format_command` quotes it for a POSIX shell. The napari
  widget's "Copy command" and the tests use it; ``fdt`` parses exactly these flags (``cli.build_parser``).
* :func:`command_for_folder` is the napari widget's "Copy command": it checks that an acquisition folder holds the
  optics and sources the run uses, writes the settings beside it and returns the line.
* :func:`config_from_file` reads a settings file (JSON or TOML, ``docs/solver.md``) or a report written by
  ``fdt reconstruct`` / the napari plugin, whose ``config`` section holds every setting of that run (seed
  included): ``fdt reconstruct ACQ --config RI.json`` reruns it.

No torch, no napari: this module handles settings and text (and reads an acquisition's metadata to compare it).
"""

from __future__ import annotations

import json
import os
import shlex
from pathlib import Path
from typing import Any, Union

from napari_fdt.errors import FDTInputError
from napari_fdt.recon.settings.config import SolverConfig, load_config
from napari_fdt.schema import scalar_type, schema_fields

__all__ = ["REPORT_FORMAT", "config_from_file", "read_report", "reconstruct_command", "format_command", "config_flags",
           "unique_path", "command_for_folder"]

PathLike = Union[str, "os.PathLike[str]"]

#: ``format`` of a reconstruction report (``RI.json``).
REPORT_FORMAT = "napari-fdt-report"


def read_report(path: PathLike) -> dict[str, Any] | None:
    """The report at ``path`` if it is a JSON object with ``"format": "napari-fdt-report"``, else None."""
    p = Path(path)
    if p.suffix.lower() != ".json":
        return None
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and data.get("format") == REPORT_FORMAT else None


def config_from_file(path: PathLike) -> SolverConfig:
    """Settings from a settings file (JSON/TOML) or from a report's ``config`` section (``RI.json``)."""
    report = read_report(path)
    if report is None:
        return load_config(path)
    config = report.get("config")
    if not isinstance(config, dict):
        raise FDTInputError("config", f"{path} is a napari-fdt report without its config section",
                            "give the report written with the volume (RI.json), or a settings file")
    return SolverConfig.from_dict(config)


def _flag_value(value: Any) -> str:
    return repr(float(value)) if isinstance(value, float) else str(value)


def config_flags(config: SolverConfig) -> list[str]:
    """The ``fdt reconstruct`` flags giving ``config`` from the defaults: one per scalar setting that differs.

    Raises :class:`FDTInputError` when a setting without a flag (``stages``) differs: such settings travel in a
    file (``SolverConfig.save``) passed as ``config``.
    """
    default = SolverConfig()
    flags: list[str] = []
    for name, info in schema_fields(SolverConfig).items():
        value, base = getattr(config, name), getattr(default, name)
        if value == base:
            continue
        kind, _ = scalar_type(info)
        if kind is None:
            raise FDTInputError("config", f"{name} differs from the default and has no command-line flag",
                                "save the settings to a file (SolverConfig.save or the widget's Save settings) and pass that file")
        flag = "--" + name.replace("_", "-")
        if kind is bool:
            flags.append(flag if value else "--no-" + name.replace("_", "-"))
        elif value is not None:
            flags += [flag, _flag_value(value)]
        else:
            raise FDTInputError("config", f"{name} is unset but the default is {base!r}; no flag unsets it",
                                "save the settings to a file and pass that file")
    return flags


def reconstruct_command(acquisition: PathLike, out: PathLike, config: SolverConfig | PathLike | None = None, *,
                        seed: int | None = None, device: str = "auto", overwrite: bool = False,
                        program: str = "fdt") -> list[str]:
    """The argument list of the ``fdt reconstruct`` run writing ``out`` from the acquisition folder ``acquisition``.

    Parameters
    ----------
    acquisition, out:
        The acquisition folder (format v1) and the RI volume to write (``.tif``/``.ome.tif``, or ``.ome.zarr``).
    config:
        The settings: a :class:`SolverConfig` (given as flags for the settings that differ from the defaults;
        refused if the stages differ, see :func:`config_flags`), the path of a settings file or of a report
        (``--config PATH``), or None for the defaults.
    seed:
        Overrides the settings' seed (``--seed``); None keeps the seed of ``config``.
    device:
        ``"auto"``, ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` (``--device``).
    overwrite:
        Adds ``--overwrite``.

    Returns
    -------
    ``[program, "reconstruct", ACQ, "--out", OUT, ...]``; :func:`format_command` makes it one shell line.
    """
    if not str(device).strip():
        raise FDTInputError("device", "is empty", "give auto, cpu or cuda")
    argv = [program, "reconstruct", os.fspath(acquisition), "--out", os.fspath(out)]
    if isinstance(config, SolverConfig):
        flags = config_flags(config)
        if seed is not None and "--seed" in flags:
            i = flags.index("--seed")
            del flags[i:i + 2]
        argv += flags
    elif config is not None:
        argv += ["--config", os.fspath(config)]
    if seed is not None:
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise FDTInputError("seed", f"must be a whole number, got {seed!r}", "give an integer seed")
        argv += ["--seed", str(seed)]
    argv += ["--device", str(device)]
    if overwrite:
        argv.append("--overwrite")
    return argv


def format_command(argv: list[str]) -> str:
    """One POSIX shell line of ``argv`` (paths with spaces or quotes quoted)."""
    return shlex.join(argv)


def unique_path(path: PathLike) -> Path:
    """``path``, or ``stem_2.suffix``, ``stem_3.suffix``, … : the first that does not exist (nothing is overwritten)."""
    path = Path(path)
    if not path.exists():
        return path
    stem, dot, suffix = path.name.partition(".")
    n = 2
    while True:
        candidate = path.with_name(f"{stem}_{n}{dot}{suffix}")
        if not candidate.exists():
            return candidate
        n += 1


def command_for_folder(folder: PathLike | None, optics: Any, sources_um: Any, config: SolverConfig, *,
                       device: str = "auto", name: str = "the acquisition") -> tuple[str, Path]:
    """The ``fdt reconstruct`` line that repeats a run of ``config`` on the acquisition folder ``folder`` with these
    ``optics`` and ``sources_um`` ((N, 3) µm, or None), and the settings file it reads.

    Refused (:class:`FDTInputError`, field ``Copy command``) when ``folder`` is no acquisition folder on disk, or when
    what it holds differs from the optics or sources given (the line would run something else). The settings are
    written beside the folder (``<folder>_settings.json``, a new name each time); the output named in the line is
    ``<folder>_RI.ome.tif`` (a new name too). ``name`` is what the messages call the acquisition.
    """
    import numpy as np

    from napari_fdt.data.io import read_acquisition

    if not folder or not (Path(folder) / "acquisition.json").is_file():
        raise FDTInputError("Copy command", f"{name} is not an acquisition folder on disk",
                            "press Save acquisition… in the FDT acquisition widget first")
    folder = Path(folder)
    on_disk = read_acquisition(folder)
    same_sources = (sources_um is None and on_disk.sources_um is None) or (
        sources_um is not None and on_disk.sources_um is not None
        and np.allclose(sources_um, on_disk.sources_um, rtol=0, atol=1e-9))
    if on_disk.optics != optics or not same_sources:
        raise FDTInputError("Copy command", f"the optics or sources of {name} differ from {folder}",
                            "press Save acquisition… in the FDT acquisition widget to write them, then copy again")
    settings = unique_path(folder.with_name(f"{folder.name}_settings.json"))
    config.save(settings)
    out = unique_path(folder.with_name(f"{folder.name}_RI.ome.tif"))
    return format_command(reconstruct_command(folder, out, settings, device=device)), settings
