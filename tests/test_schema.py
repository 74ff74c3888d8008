"""The settings schema: one declaration per setting, read by the errors, the docs table, the CLI flags and the widgets."""

from __future__ import annotations

import dataclasses
import importlib.util
import math
from pathlib import Path

import pytest

from napari_fdt.errors import FDTInputError
from napari_fdt.physics.optics import OPTICS_FIELDS, Optics
from napari_fdt.recon.problem.losses import LossWeights
from napari_fdt.recon.settings.config import COARSE_MODELS, SolverConfig, StageConfig, settings_markdown
from napari_fdt.schema import bounds, choices, example, scalar_type, schema_fields

ROOT = Path(__file__).resolve().parents[1]


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_docs_settings_table_is_the_generated_one() -> None:
    table = _script("settings_table")
    text = (ROOT / "docs" / "settings.md").read_text(encoding="utf-8")
    assert table.rewrite(text) == text, "docs/settings.md is out of date: python scripts/settings_table.py --write"
    # every field is in it, with its bounds and its choices
    for name in schema_fields(SolverConfig):
        assert f"| `{name}` |" in text
    assert "| `batch_size` | basic | int ≥ 1 | 16 | images per iteration |" in settings_markdown()
    assert '`"auto"` \\| `"envelope"` \\| `"multislice"`' in settings_markdown()


def test_fields_carry_types_bounds_choices_and_descriptions() -> None:
    fields = schema_fields(SolverConfig)
    assert all(info.description for info in fields.values())
    assert bounds(fields["batch_size"]) == {"ge": 1} and scalar_type(fields["batch_size"]) == (int, False)
    assert bounds(fields["mask_threshold"]) == {"gt": 0, "lt": 1}
    assert bounds(fields["source_depth_um"]) == {"gt": 0} and scalar_type(fields["source_depth_um"]) == (float, True)
    assert choices(fields["coarse_model"]) == COARSE_MODELS and scalar_type(fields["coarse_model"]) == (str, False)
    assert scalar_type(fields["calibrate_gain"]) == (bool, False) and scalar_type(fields["stages"])[0] is None
    assert tuple(schema_fields(Optics)) == OPTICS_FIELDS
    assert example(schema_fields(Optics)["na"]) == 0.8 and example(schema_fields(Optics)["image_plane_um"]) == 0.0


@pytest.mark.parametrize(
    "data,message",
    [
        ({"batch_size": 0}, "batch_size: must be >= 1, got 0 (give a value >= 1)"),
        ({"batch_size": 2.0}, "batch_size: must be a valid integer, got 2.0 (write a whole number)"),
        ({"lr_ri": "0.1"}, "lr_ri: must be a valid number, got '0.1' (write a plain number)"),
        ({"calibrate_gain": 1}, "calibrate_gain: must be a valid boolean, got 1 (write true or false)"),
        ({"ssim_weight": math.inf}, "ssim_weight: must be a finite number, got inf (0 switches the term off)"),
        ({"stages": [{"factor": 0}]},
         "stages[].factor: must be >= 1, got 0 (use 4, 2, 1 for three stages)"),
        ({"stages": [{"factor": 1, "iters": 3}]}, "stages[].iters: is not a setting (known settings: factor, iterations, batch_size)"),
        ({"l1_ramp_start": 0.6, "l1_ramp_end": 0.5},
         "l1_ramp_start: must satisfy 0 <= l1_ramp_start <= l1_ramp_end <= 1, got 0.6 > 0.5 (the L1 weight rises over this fraction of the run)"),
    ],
)
def test_one_adapter_writes_field_problem_fix(data: dict, message: str) -> None:
    with pytest.raises(FDTInputError) as exc:
        SolverConfig.from_dict(data)
    assert str(exc.value) == message
    assert str(exc.value).startswith(exc.value.field + ": ")


def test_literal_errors_list_the_choices() -> None:
    with pytest.raises(FDTInputError) as exc:
        SolverConfig(backward_mode="fast")
    assert exc.value.field == "backward_mode" and "'checkpoint'" in exc.value.problem and "fits in memory" in exc.value.fix


def test_removed_backward_mode_fused_loads_as_auto_with_a_warning(tmp_path) -> None:
    """Settings files and reports (RI.json) written while ``backward_mode = "fused"`` existed still load: the value
    becomes "auto", with an FDTWarning naming the replacement and why the value went; it is no longer a choice."""
    import json

    from napari_fdt.errors import FDTWarning
    from napari_fdt.recon.settings.command import REPORT_FORMAT, config_from_file

    data = {"backward_mode": "fused", "stages": [{"factor": 1, "iterations": 5}]}
    with pytest.warns(FDTWarning, match=r'backward_mode: "fused" was removed on 2026-11-26: slower than the FFT loop on '
                                        r'an H200, docs/decisions/gpu-checklist-h200.md; using "auto"'):
        assert SolverConfig.from_dict(data).backward_mode == "auto"
    settings = tmp_path / "settings.json"
    settings.write_text(json.dumps(data), encoding="utf-8")
    report = tmp_path / "RI.json"
    report.write_text(json.dumps({"format": REPORT_FORMAT, "config": data}), encoding="utf-8")
    for path in (settings, report):
        with pytest.warns(FDTWarning, match="removed"):
            assert config_from_file(path).backward_mode == "auto"
    assert "fused" not in choices(schema_fields(SolverConfig)["backward_mode"])


def test_replace_validates_again_and_stages_keep_their_prefix() -> None:
    cfg = SolverConfig(stages=[StageConfig(2, 3), StageConfig(1, 4)])
    assert dataclasses.replace(cfg, tv_xy_weight=1e-3).tv_xy_weight == 1e-3
    with pytest.raises(FDTInputError) as exc:
        dataclasses.replace(cfg, mask_threshold=1.0)
    assert exc.value.field == "mask_threshold"
    with pytest.raises(FDTInputError) as exc:
        StageConfig(1, -1)
    assert exc.value.field == "stages[].iterations"


def test_optics_schema_keeps_its_checks() -> None:
    base = dict(wavelength_um=0.6, n_background=1.33, na=0.8, pixel_size_um=0.3, n_slices=4.0, slice_spacing_um=2.0)
    o = Optics(**base)
    assert o.n_slices == 4 and isinstance(o.n_slices, int) and o.image_plane_um == 0.0
    assert dataclasses.replace(o, n_slices=6).thickness_um == 12.0
    for field, bad in [("n_slices", 4.5), ("n_slices", True), ("wavelength_um", 0.0), ("pixel_size_um", math.nan),
                       ("n_background", 0.9), ("image_plane_um", math.inf), ("na", "0.5")]:
        with pytest.raises(FDTInputError) as exc:
            Optics(**{**base, field: bad})
        assert exc.value.field == field, str(exc.value)
    with pytest.raises(FDTInputError, match=r"^na: numerical aperture 1.4 is not below n_background 1.33"):
        Optics(**{**base, "na": 1.4})
    assert Optics.examples() == dict(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=8,
                                     slice_spacing_um=2.0, image_plane_um=0.0)


def test_loss_weights_come_from_the_config() -> None:
    cfg = SolverConfig(l1_l2_total=2.0, ssim_weight=0.1, tv_xy_weight=1e-3, tv_z_weight=2e-3, l1_ramp_start=0.2, l1_ramp_end=0.7)
    assert LossWeights.from_config(cfg) == LossWeights(2.0, 0.1, 1e-3, 2e-3, 0.2, 0.7)


def test_settings_come_in_tiers_and_the_help_lists_them_in_order() -> None:
    """The few a user sets first, the experimental ones apart (issue 24's list), each flag in its tier's group."""
    from napari_fdt.cli import build_parser
    from napari_fdt.schema import TIERS, tier

    fields = schema_fields(SolverConfig)
    by_tier = {t: [n for n, info in fields.items() if tier(info) == t] for t in TIERS}
    assert by_tier["basic"] == ["stages", "batch_size", "tv_xy_weight", "tv_z_weight", "calibrate_sources", "seed",
                                "validation_fraction", "tv_family"]
    assert set(by_tier["experimental"]) == {"source_step", "calibrate_sources_in_envelope_stages",
                                            "calibrate_source_depth_in_envelope_stages", "restart_source_moments",
                                            "multislice_source_step_scale", "source_step_schedule", "lr_ri_final_ratio",
                                            "parts_rerun", "parts_test_images", "parts_backward", "parts_branch"}
    assert sum(map(len, by_tier.values())) == len(fields)
    rows = [line for line in settings_markdown().splitlines() if line.startswith("| `")]
    tiers_in_table = [line.split("|")[2].strip() for line in rows[: len(fields)]]
    assert tiers_in_table == sorted(tiers_in_table, key=TIERS.index)  # basic rows first, experimental last
    help_text = build_parser().parse_args.__self__._subparsers._group_actions[0].choices["reconstruct"].format_help()
    first, advanced, experimental = (help_text.index(h) for h in ("solver settings (", "advanced solver settings",
                                                                  "experimental solver settings"))
    flag = lambda name: help_text.index("\n  --" + name)  # noqa: E731  (its line in the groups, not in the usage)
    assert first < flag("batch-size") < advanced < flag("coarse-model") < experimental < flag("source-step ")
    assert flag("parts-rerun") > experimental
