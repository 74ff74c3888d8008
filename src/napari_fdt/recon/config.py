"""Every solver setting, in one JSON-serialisable configuration shared by the API, ``fdt`` and napari.

``docs/solver.md`` documents each field. ``SolverConfig.from_dict`` rejects unknown keys (a typo would
otherwise be silently ignored) and validates values, naming the field and the fix.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from napari_fdt.errors import FDTInputError

__all__ = ["StageConfig", "SolverConfig", "load_config", "COHERENCE_MODELS", "BACKWARD_MODES", "COARSE_MODELS", "resolve_coarse_model"]

COHERENCE_MODELS = ("none", "mask", "spectral", "mask+spectral")
#: Model of the coarse stages; "auto": the envelope model on a CPU (12× cheaper than multi-slice there),
#: multi-slice on a GPU (where the envelope model's many small kernels made it slower; docs/benchmarks.md).
COARSE_MODELS = ("auto", "envelope", "multislice")
#: How the multi-slice model forms gradients (:mod:`napari_fdt.model.slice_loop`); "autograd" is the plain reference.
BACKWARD_MODES = ("auto", "stored", "reversible", "checkpoint", "autograd")


@dataclass
class StageConfig:
    """One coarse-to-fine stage: lateral ``factor`` (stage pixel = factor × acquisition pixel), ``iterations``
    and optionally its own ``batch_size`` (None: the configuration's). A coarse stage's images are
    ``factor²`` times smaller: on a GPU, where a small step costs its kernel launches rather than its
    arithmetic, a larger batch there uses more data for about the same time per iteration."""

    factor: int = 1
    iterations: int = 100
    batch_size: int | None = None

    def __post_init__(self) -> None:
        if isinstance(self.factor, bool) or not isinstance(self.factor, int) or self.factor < 1:
            raise FDTInputError("stages[].factor", f"must be an integer >= 1, got {self.factor!r}", "use 4, 2, 1 for three stages")
        if isinstance(self.iterations, bool) or not isinstance(self.iterations, int) or self.iterations < 0:
            raise FDTInputError("stages[].iterations", f"must be an integer >= 0, got {self.iterations!r}", "e.g. 100")
        if self.batch_size is not None and (isinstance(self.batch_size, bool) or not isinstance(self.batch_size, int) or self.batch_size < 1):
            raise FDTInputError("stages[].batch_size", f"must be an integer >= 1 or null, got {self.batch_size!r}",
                                "leave it out to use the configuration's batch_size")


def _default_stages() -> list[StageConfig]:
    return [StageConfig(4, 100), StageConfig(2, 100), StageConfig(1, 160)]


@dataclass
class SolverConfig:
    """Settings of a reconstruction. Learning rates are Adam step sizes in the parameters' own units."""

    # coarse-to-fine
    stages: list[StageConfig] = field(default_factory=_default_stages)
    coarse_model: str = "auto"
    batch_size: int = 16
    # RI grid
    delta_n_max: float = 0.1
    activation: str = "paper"
    lr_ri: float = 0.05
    # losses
    l1_l2_total: float = 1.0
    l1_ramp_start: float = 0.0
    l1_ramp_end: float = 1.0
    ssim_weight: float = 0.0
    tv_xy_weight: float = 0.0
    tv_z_weight: float = 0.0
    # self-calibration
    calibrate_sources: bool = True
    calibrate_gain: bool = True
    calibrate_source_depth: bool = True
    calibrate_pixel_size: bool = False
    calibrate_slice_spacing: bool = False
    calibration_from_stage: int = 1
    lr_sources_um: float = 0.02
    lr_log_gain: float = 0.01
    lr_global: float = 1e-3
    source_depth_um: float | None = None
    # partial coherence
    coherence: str = "none"
    mask_threshold: float = 0.5
    bandwidth_um: float = 0.03
    n_wavelengths: int = 3
    # run
    seed: int = 0
    snapshot_every: int = 10
    backward_mode: str = "auto"
    obliquity_correction: bool = False

    def __post_init__(self) -> None:
        self._check_types()
        self.stages = [s if isinstance(s, StageConfig) else StageConfig(**_only(s, StageConfig, "stages[]")) for s in self.stages]
        if not self.stages:
            raise FDTInputError("stages", "is empty", "give at least one stage, e.g. [{\"factor\": 1, \"iterations\": 100}]")
        for a, b in zip(self.stages, self.stages[1:]):
            if a.factor % b.factor:
                raise FDTInputError("stages", f"factor {a.factor} is followed by {b.factor}, which does not divide it",
                                    "use decreasing factors that divide each other, e.g. 4, 2, 1")
        _positive_int("batch_size", self.batch_size)
        _positive_int("snapshot_every", self.snapshot_every)
        _positive_int("n_wavelengths", self.n_wavelengths)
        for name in ("delta_n_max", "lr_ri", "lr_sources_um", "lr_log_gain", "lr_global"):
            _positive(name, getattr(self, name))
        for name in ("l1_l2_total", "ssim_weight", "tv_xy_weight", "tv_z_weight", "bandwidth_um"):
            _non_negative(name, getattr(self, name))
        if not (0.0 <= self.l1_ramp_start <= self.l1_ramp_end <= 1.0):
            raise FDTInputError("l1_ramp_start", "must satisfy 0 <= l1_ramp_start <= l1_ramp_end <= 1",
                                "the L1 weight rises over this fraction of the run")
        if self.coarse_model not in COARSE_MODELS:
            raise FDTInputError("coarse_model", f"unknown model {self.coarse_model!r}", f"choose one of {', '.join(COARSE_MODELS)}")
        if self.backward_mode not in BACKWARD_MODES:
            raise FDTInputError("backward_mode", f"unknown mode {self.backward_mode!r}",
                                f"choose one of {', '.join(BACKWARD_MODES)} (auto picks the fastest that fits in memory)")
        if self.activation not in ("paper", "signed"):
            raise FDTInputError("activation", f"unknown activation {self.activation!r}", "choose paper or signed")
        if self.coherence not in COHERENCE_MODELS:
            raise FDTInputError("coherence", f"unknown model {self.coherence!r}", f"choose one of {', '.join(COHERENCE_MODELS)}")
        if not (0.0 < self.mask_threshold < 1.0):
            raise FDTInputError("mask_threshold", f"must be in (0, 1), got {self.mask_threshold}", "the paper binarises at about 0.5 of the maximum")
        if self.source_depth_um is not None:
            _positive("source_depth_um", self.source_depth_um)
        if isinstance(self.calibration_from_stage, bool) or not isinstance(self.calibration_from_stage, int) or self.calibration_from_stage < 0:
            raise FDTInputError("calibration_from_stage", f"must be an integer >= 0, got {self.calibration_from_stage!r}", "0 calibrates from the start")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise FDTInputError("seed", f"must be an integer, got {self.seed!r}", "e.g. 0")

    def _check_types(self) -> None:
        """Every field has the JSON type its default has (numbers may be int or float; source_depth_um may be null)."""
        if not isinstance(self.stages, list):
            raise FDTInputError("stages", f"must be a list of {{factor, iterations}} objects, got {self.stages!r}",
                                "e.g. [{\"factor\": 2, \"iterations\": 50}, {\"factor\": 1, \"iterations\": 100}]")
        for f in fields(self):
            if f.name == "stages":
                continue
            value = getattr(self, f.name)
            default = getattr(SolverConfig, f.name, None)
            if f.name == "source_depth_um":
                if value is None:
                    continue
                default = 1.0
            if isinstance(default, bool):
                ok = isinstance(value, bool)
                want = "true or false"
            elif isinstance(default, (int, float)):
                ok = isinstance(value, (int, float)) and not isinstance(value, bool)
                want = "a number"
            else:
                ok = isinstance(value, str)
                want = "a string"
            if not ok:
                raise FDTInputError(f.name, f"must be {want}, got {value!r}", "see docs/solver.md for each setting")

    def stage_batch(self, stage_index: int) -> int:
        """Batch size of a stage: its own ``batch_size``, else the configuration's."""
        b = self.stages[stage_index].batch_size
        return self.batch_size if b is None else b

    @property
    def total_iterations(self) -> int:
        return sum(s.iterations for s in self.stages)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "SolverConfig":
        return cls(**_only(data, cls, "config"))

    def save(self, path: str | Path) -> None:
        from napari_fdt.data.io import write_json_atomic

        write_json_atomic(path, self.to_dict(), overwrite=True)


def resolve_coarse_model(coarse_model: str, device_type: str) -> str:
    """``"auto"`` → ``"multislice"`` on CUDA, ``"envelope"`` elsewhere; other values pass through."""
    if coarse_model != "auto":
        return coarse_model
    return "multislice" if device_type == "cuda" else "envelope"


def _only(data: Any, klass, where: str) -> dict:
    if not isinstance(data, dict):
        raise FDTInputError(where, f"must be a JSON object, got {type(data).__name__}", "see docs/solver.md")
    known = {f.name for f in fields(klass)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise FDTInputError(f"{where}.{unknown[0]}", "is not a setting", f"known settings: {', '.join(sorted(known))}")
    return data


def _positive_int(name: str, v: Any) -> None:
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise FDTInputError(name, f"must be an integer >= 1, got {v!r}", "give a positive whole number")


def _positive(name: str, v: Any) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise FDTInputError(name, f"must be a positive number, got {v!r}", "give a finite value > 0")


def _non_negative(name: str, v: Any) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
        raise FDTInputError(name, f"must be a number >= 0, got {v!r}", "0 switches the term off")


def load_config(path: str | Path) -> SolverConfig:
    """Read a configuration file (JSON; also TOML when the name ends in .toml)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise FDTInputError("config", f"cannot read {p}: {exc.strerror or exc}", "check the path") from None
    try:
        if p.suffix.lower() == ".toml":
            try:
                import tomllib
            except ImportError:  # Python 3.10
                raise FDTInputError("config", "TOML needs Python >= 3.11", "write the configuration as JSON") from None
            data = tomllib.loads(text)
        else:
            data = json.loads(text)
    except (ValueError, json.JSONDecodeError) as exc:
        raise FDTInputError("config", f"{p} does not parse: {exc}", "write valid JSON (or TOML for .toml)") from None
    return SolverConfig.from_dict(data)
