"""Which model each stage uses, answered by one rule (recon/problem/stage_spec.py, issue 52 item 4): the solver's
stages, the plan's prices and the memory check read the same answer; the parts switch it as documented."""

from __future__ import annotations

import pytest

from napari_fdt.recon.problem.stage_spec import AUTO_SUB_SLICES, CameraModel, stage_spec
from napari_fdt.recon.settings.config import SolverConfig, StageConfig

CAMERA = CameraModel(pupil_edge=0.03, pixel_integration=False)


def _config(**kw) -> SolverConfig:
    return SolverConfig(stages=[StageConfig(4, 2), StageConfig(2, 2), StageConfig(1, 2)], **kw)


def test_the_rule_of_each_part() -> None:
    cfg = _config(sub_slices="auto", field_oversampling="auto")
    none = [stage_spec(cfg, i, "envelope", set(), CAMERA) for i in range(3)]
    assert [s.envelope for s in none] == [True, True, False]
    assert [s.screens_per_slice for s in none] == [1, 1, 1] and not any(s.fine_grid for s in none)
    on = [stage_spec(cfg, i, "multislice", {"sub_slices", "field_grid", "obliquity", "pixel_integration"}, CAMERA) for i in range(3)]
    assert [s.envelope for s in on] == [False, False, False]
    # the sub-slices and the 2x grid are the finest stage's only; obliquity and the camera's integration every stage's
    assert [s.sub_slices for s in on] == [1, 1, AUTO_SUB_SLICES] and [s.fine_grid for s in on] == [False, False, True]
    assert all(s.obliquity == "per_source" and s.pixel_integration for s in on)
    numbers = stage_spec(_config(sub_slices=3, field_oversampling=2), 1, "multislice", set(), CAMERA)
    assert numbers.sub_slices == 3 and numbers.field_oversampling == 2 and not numbers.fine_grid  # a factor-2 stage
    assert CameraModel(0.0, True).parts_on() == {"pixel_integration"} and CAMERA.parts_on() == frozenset()


@pytest.mark.filterwarnings("ignore")
def test_the_solver_builds_the_model_its_spec_states(scene16) -> None:
    """Each stage the solver builds runs the model its spec states; the plan prices the same screens."""
    from napari_fdt.model.envelope import EnvelopeModel
    from napari_fdt.model.oversampled import OversampledModel
    from napari_fdt.recon.run.solver import Reconstructor

    cfg = SolverConfig(stages=[StageConfig(2, 1), StageConfig(1, 1)], batch_size=4, final_stage_min_passes=0, tv_xy_weight=0.0,
                       tv_z_weight=0.0, sub_slices="auto", field_oversampling="auto", coarse_model="envelope")
    rec = Reconstructor(scene16.acquisition, cfg, device="cpu")
    rec.parts.update(sub_slices=True, field_grid=True, obliquity=True)
    for i in range(2):
        spec, stage = rec.stage_spec(i), rec._build_stage(i)
        assert isinstance(stage.model, EnvelopeModel) == spec.envelope == (i == 0)
        if not spec.envelope:
            assert isinstance(stage.model, OversampledModel) == spec.fine_grid is True
            inner = getattr(stage.model, "inner", stage.model)  # (the 2x grid's multi-slice model)
            assert inner.sub_slices == spec.sub_slices == AUTO_SUB_SLICES
            assert inner.obliquity == spec.obliquity == "per_source"
            assert stage.model.pixel_integration == spec.pixel_integration
        phase = rec._stage_phase(i, "run", ("sub_slices", "field_grid", "obliquity"))
        assert phase.model == ("envelope" if spec.envelope else "multislice")
    fine = rec._stage_phase(1, "run", ("sub_slices",)).seconds_per_iteration
    assert fine > rec._stage_phase(1, "run", ()).seconds_per_iteration  # the screens the spec adds are priced
