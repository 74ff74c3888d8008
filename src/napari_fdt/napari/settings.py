"""Solver settings as the reconstruction widget shows them: the stage list as text, and checked configs.

The widget edits a subset of :class:`~napari_fdt.recon.config.SolverConfig`; the other settings keep the
values of the last loaded settings file (or the defaults), so that saving writes a complete file in the
format of ``fdt reconstruct --config``.
"""

from __future__ import annotations

import re
from typing import Any

from napari_fdt.errors import FDTInputError
from napari_fdt.recon.config import SolverConfig, StageConfig

__all__ = ["format_stages", "parse_stages", "merge_config"]

_STAGE = re.compile(r"^\s*(\d+)\s*[x×:*]\s*(\d+)\s*(?:@\s*(\d+)\s*)?$")
_STAGES_FIX = ("write factor x iterations per stage, comma separated, e.g. 4x100, 2x100, 1x160 "
               "(a stage's own batch size after @, e.g. 4x100@64)")


def format_stages(stages: list[StageConfig]) -> str:
    """``[StageConfig(4, 100, 64), StageConfig(1, 160)]`` → ``"4x100@64, 1x160"`` (``@`` a stage's own batch size)."""
    return ", ".join(f"{s.factor}x{s.iterations}" + ("" if s.batch_size is None else f"@{s.batch_size}") for s in stages)


def parse_stages(text: str) -> list[dict[str, int]]:
    """``"4x100, 2x100, 1x160"`` (also ``×``, ``:`` or ``*``; ``4x100@64`` gives the stage batch 64) →
    ``[{"factor": 4, "iterations": 100}, …]``."""
    parts = [p for p in str(text).split(",") if p.strip()]
    if not parts:
        raise FDTInputError("stages", "is empty", _STAGES_FIX)
    out = []
    for part in parts:
        m = _STAGE.match(part)
        if not m:
            raise FDTInputError("stages", f"cannot read {part.strip()!r}", _STAGES_FIX)
        stage = {"factor": int(m.group(1)), "iterations": int(m.group(2))}
        if m.group(3) is not None:
            stage["batch_size"] = int(m.group(3))
        out.append(stage)
    return out


def merge_config(base: SolverConfig, values: dict[str, Any]) -> SolverConfig:
    """``base`` with ``values`` replaced (``stages`` may be the widget's text), validated by :class:`SolverConfig`."""
    data = base.to_dict()
    values = dict(values)
    if isinstance(values.get("stages"), str):
        values["stages"] = parse_stages(values["stages"])
    data.update(values)
    return SolverConfig.from_dict(data)
