"""The roles of a run's stages: which run the envelope model, and in which the source positions or depths stay fixed
(they follow the configuration and the coarse model a run resolved; :class:`~napari_fdt.recon.calibration.calibration.Calibration`
reads them as sets of stage indices).
"""

from __future__ import annotations

from napari_fdt.recon.calibration.calibration import Calibration
from napari_fdt.recon.problem.stage_spec import runs_envelope
from napari_fdt.recon.settings.config import SolverConfig

__all__ = ["envelope_stages", "position_frozen_stages", "depth_frozen_stages", "set_stage_roles"]


def envelope_stages(config: SolverConfig, coarse_model: str) -> frozenset[int]:
    """Stages that run the envelope model: factor > 1 with ``coarse_model`` ``"envelope"`` (as :func:`~napari_fdt.recon.problem.stages.build_stage`)."""
    return frozenset(i for i, s in enumerate(config.stages) if runs_envelope(s.factor, coarse_model))


def _envelope_stages_before_multislice(config: SolverConfig, coarse_model: str) -> frozenset[int]:
    """The envelope stages that a multi-slice stage follows (none when every stage is an envelope one)."""
    env = envelope_stages(config, coarse_model)
    return frozenset(i for i in env if not all(j in env for j in range(i, len(config.stages))))


def position_frozen_stages(config: SolverConfig, coarse_model: str) -> frozenset[int]:
    """Stages whose source positions and depth offset stay fixed: with ``calibrate_sources_in_envelope_stages`` off, the
    envelope stages (factor > 1, ``coarse_model`` ``"envelope"``) that a multi-slice stage follows. Fitted with the volume
    at the truth, the envelope model pulls the positions off (``docs/decisions/source-steps.md``)."""
    if config.calibrate_sources_in_envelope_stages:
        return frozenset()
    return _envelope_stages_before_multislice(config, coarse_model)


def depth_frozen_stages(config: SolverConfig, coarse_model: str) -> frozenset[int]:
    """Stages whose source depths (each source's own and the common offset) stay fixed while x, y train: with
    ``calibrate_source_depth_in_envelope_stages`` off, the envelope stages that a multi-slice stage follows."""
    if config.calibrate_source_depth_in_envelope_stages:
        return frozenset()
    return _envelope_stages_before_multislice(config, coarse_model)


def set_stage_roles(cal: Calibration, config: SolverConfig, coarse_model: str) -> None:
    """Tell ``cal`` which stages run the envelope model and in which its positions or depths stay fixed (they
    follow ``coarse_model``, the run's coarse stages' model after resolving "auto")."""
    cal.position_frozen_stages = position_frozen_stages(config, coarse_model)
    cal.depth_frozen_stages = depth_frozen_stages(config, coarse_model)
    cal.envelope_stages = envelope_stages(config, coarse_model)
