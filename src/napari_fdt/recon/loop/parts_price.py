"""The price of the model parts' tests (issue 48, item 3): what the choice of the ``"auto"`` parts costs besides the
stages' iterations, in the plan's own unit, a training step's seconds per image of the model a test runs.

The tests (:mod:`napari_fdt.recon.choices.parts_search`, :mod:`~napari_fdt.recon.choices.parts_coarse_end`) predict
images without gradients and fit the pupil's parameters through a cached exit field:

- at the finest stage's end: the test images once as they are (the reference), once per binary part to choose with
  that part's model (the 2x field grid on at most :data:`~napari_fdt.recon.loop.model_parts.GRID_TRIAL_TRAINING_IMAGES`
  training images), the stage built again for each; then, where the pupil or the aberrations are to choose, the
  fit images' exit field once and per part :data:`~napari_fdt.recon.loop.model_parts.FIT_ITERATIONS` fit steps on the
  :data:`~napari_fdt.recon.loop.model_parts.FIT_IMAGES` fit images and the test images again;
- where the trial through the volume rejects sub-slices or the 2x field grid, a branch of training
  (:mod:`napari_fdt.recon.choices.parts_branch`): its iterations without the part and with it, and the held-out images
  predicted at each arm's end;
- at the last coarse stage's end (:func:`~napari_fdt.recon.loop.model_parts.coarse_end_test_planned`): the finest
  stage built, its reference, and the aberrations' fit and prediction.

The test images are the held-out ones and, with ``parts_test_images`` ``"held_out+training"`` (the default), the
training images the fits do not use. The constants were measured on the suite's scenes (docs/benchmarks.md, "The
plan prices the parts' tests").
"""

from __future__ import annotations

from typing import Callable

from napari_fdt.recon.loop.model_parts import (
    BINARY_PARTS,
    FINEST_ONLY_PARTS,
    FIT_IMAGES,
    FIT_ITERATIONS,
    FITTED_PARTS,
    GRID_TRIAL_TRAINING_IMAGES,
    branch_iterations,
)

__all__ = ["PREDICT_SHARE", "FIT_SHARE", "FIT_STEP_S", "TRIAL_SETUP_S", "test_images", "finest_test_setup", "part_costs",
           "finest_end_test_s", "coarse_end_test_s"]

#: One image predicted without gradients over one image's share of a training step of the same model.
PREDICT_SHARE = 0.3
#: One fit image's share of a pupil fit step (through the cached exit field: the camera's part of the model only)
#: over one image's share of a training step.
FIT_SHARE = 0.3
#: Seconds of a fit step that do not scale with the images (the pupil's kernels made again), by device type.
FIT_STEP_S: dict[str, float] = {"cpu": 0.010, "cuda": 0.010}
#: Seconds of a trial's set-up (the stage built again with the part: its images, its model's tables), by device type.
TRIAL_SETUP_S: dict[str, float] = {"cpu": 0.2, "cuda": 0.1}


def test_images(n_images: int, n_held: int, parts_test_images: str) -> tuple[int, int]:
    """(the test images, the fit images) of an acquisition of ``n_images`` with ``n_held`` held out."""
    n_fit = min(FIT_IMAGES, max(0, n_images - n_held))
    n_test = n_held + (n_images - n_held - n_fit if parts_test_images == "held_out+training" else 0)
    return n_test, n_fit


def finest_test_setup(config, n_images: int, n_held: int) -> tuple[int, int, int]:
    """(the test images, the fit images, the images one arm of a branch trial trains on: 0 without branches) of the
    tests at the finest stage's end of a run of ``config`` (a :class:`~napari_fdt.recon.settings.config.SolverConfig`)."""
    last = len(config.stages) - 1
    n_test, n_fit = test_images(n_images, n_held, config.parts_test_images)
    branch = branch_iterations(config.stages[last].iterations) * config.stage_batch(last) if config.parts_branch and n_held >= 2 else 0
    return n_test, n_fit, branch


def part_costs(base_s: float, image_s: Callable[[tuple[str, ...]], float], parts: tuple[str, ...] | list[str]) -> dict[str, float]:
    """:func:`finest_end_test_s`'s ``image_s``: ``base_s`` under key ``""``, and ``image_s((part,))`` for each binary part
    among ``parts`` (a training step's seconds per image of the model with that part on)."""
    return {"": base_s, **{p: image_s((p,)) for p in BINARY_PARTS if p in parts}}


def _fitted_s(image_s: float, n_test: int, n_fit: int, n_parts: int, device_type: str) -> float:
    """The fitted parts' tests: the exit cache, then per part the fit steps and the test images."""
    if n_parts == 0:
        return 0.0
    fit_step = n_fit * FIT_SHARE * image_s + FIT_STEP_S[device_type]
    return n_fit * PREDICT_SHARE * image_s + n_parts * (FIT_ITERATIONS * fit_step + n_test * PREDICT_SHARE * image_s)


def finest_end_test_s(image_s: dict[str, float], auto_parts: tuple[str, ...], n_test: int, n_fit: int, n_held: int,
                      device_type: str, branch_images: int = 0) -> float:
    """Seconds of the test at the finest stage's end. ``image_s``: a training step's seconds per image of the finest
    stage's model, as it is (key ``""``) and with each binary part in ``auto_parts`` on (key: the part);
    ``branch_images``: the images one arm of a branch trial trains on (its iterations × the batch; 0 without branches;
    priced wherever the part is to choose: the trial through the volume rejects it on most scenes)."""
    base = image_s[""]
    total = n_test * PREDICT_SHARE * base
    for part in (p for p in BINARY_PARTS if p in auto_parts):
        n = n_held + min(n_test - n_held, GRID_TRIAL_TRAINING_IMAGES) if part == "field_grid" else n_test
        total += TRIAL_SETUP_S[device_type] + n * PREDICT_SHARE * image_s[part]
        if branch_images and part in FINEST_ONLY_PARTS:
            total += (branch_images + n_held * PREDICT_SHARE) * (base + image_s[part]) + TRIAL_SETUP_S[device_type]
    return total + _fitted_s(base, n_test, n_fit, sum(p in auto_parts for p in FITTED_PARTS), device_type)


def coarse_end_test_s(image_s: float, n_test: int, n_fit: int, device_type: str) -> float:
    """Seconds of the aberrations' test at the last coarse stage's end, through the finest stage's model (``image_s``:
    its training step's seconds per image): the stage built, its reference, the fit and the prediction."""
    return TRIAL_SETUP_S[device_type] + n_test * PREDICT_SHARE * image_s + _fitted_s(image_s, n_test, n_fit, 1, device_type)
