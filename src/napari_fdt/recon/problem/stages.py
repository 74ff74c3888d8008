"""Coarse-to-fine stages: a coarse RI grid, and the field and images on the coarsest grid the optics allow.

A stage with ``factor`` f holds the RI on pixels of ``f·dx``. The field, however, must resolve the pupil:
its sampling ``g·dx`` (``g`` the *field factor*, a divisor of f) is the coarsest that keeps the pupil's
outer edge below 95 % of the grid's Nyquist frequency, ``g·dx ≤ 0.95·λ/(2·NA·(1 + pupil_taper))``. The
RI is upsampled from the stage grid to the field grid inside the model, and the measured images are
averaged over g×g blocks. When the camera oversamples the pupil, early stages are cheaper by ``g²``;
on data sampled near the pupil's Nyquist limit (g = 1) every stage costs the same per iteration and the
coarse stages act as a coarse parameterisation of the RI only. (A coarse *field* grid with a reduced
aperture was tried and rejected: at the low Fresnel numbers of a reduced aperture the images are
dominated by its edge diffraction, 39 % residual on a homogeneous medium at f = 4; ``docs/solver.md``.)

Coordinates: coarse pixel j averages fine pixels ``j·f … j·f + f − 1``, so its centre sits at
``x = (j·f + (f − 1)/2 − W//2)·dx``, while a model on that grid puts pixel j at ``(j − w//2)·f·dx``. The
difference ``shift_um`` is subtracted from source positions given to the stage model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from napari_fdt.errors import FDTInputError
from napari_fdt.model.envelope import EnvelopeModel
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.model.oversampled import OversampledModel
from napari_fdt.model.protocol import ImageModel
from napari_fdt.model.split_field import SplitFieldModel, split_plan
from napari_fdt.physics.grid import DEFAULT_PUPIL_TAPER, GridPlan, plan_grid
from napari_fdt.physics.optics import Optics
from napari_fdt.recon.problem.stage_images import LazyImages, block_average, stage_images
from napari_fdt.recon.problem.stage_spec import CameraModel, fine_field_grid, runs_envelope, stage_field_oversampling
from napari_fdt.recon.problem.volume import upsample_to

__all__ = ["Stage", "build_stage", "thick_slices", "SUB_SLICE_MIN_DOF_RATIO",
           "camera_grid_drops_band",
           "uses_split_field", "config_uses_split_field", "split_window_fraction",
           "model_window", "block_average", "stage_optics", "field_factor", "multislice_plan", "camera_model_options",
           "camera_model", "stated_pixel_integration", "resolved_pixel_integration"]

#: Fraction of the coarse grid's Nyquist frequency the stage pupil's outer edge may reach.
NYQUIST_FILL = 0.95


def field_factor(optics: Optics, factor: int, pupil_taper: float = DEFAULT_PUPIL_TAPER) -> int:
    """Largest divisor g of ``factor`` with ``g·dx ≤ NYQUIST_FILL·λ/(2·NA·(1 + pupil_taper))`` (at least 1)."""
    limit = NYQUIST_FILL * optics.wavelength_um / (2.0 * optics.na * (1.0 + pupil_taper))
    best = 1
    for g in range(1, factor + 1):
        if factor % g == 0 and g * optics.pixel_size_um <= limit:
            best = g
    return best


def stage_optics(optics: Optics, field_factor_: int) -> Optics:
    """The acquisition's optics sampled at ``field_factor_ · dx``."""
    return Optics(
        wavelength_um=optics.wavelength_um, n_background=optics.n_background, na=optics.na,
        pixel_size_um=optics.pixel_size_um * field_factor_, n_slices=optics.n_slices,
        slice_spacing_um=optics.slice_spacing_um, image_plane_um=optics.image_plane_um,
    )


@dataclass
class Stage:
    """Everything fixed during one stage.

    ``factor``: RI grid factor; ``field_factor``: field/image grid factor (divides ``factor``).
    ``images``: measured images averaged to the field grid (N, h_f, w_f), normalised by the acquisition's mean.
    ``shift_um``: (x, y) to subtract from source positions for the stage model.
    """

    index: int
    factor: int
    field_factor: int
    iterations: int
    optics: Optics
    model: ImageModel
    images: torch.Tensor | LazyImages
    shift_um: tuple[float, float]
    grid_shape: tuple[int, int]
    window: tuple[int, int]
    coverage: torch.Tensor | None = None
    _shift: dict = field(default_factory=dict, repr=False, compare=False)  # stage_sources' tensors, per device and dtype

    @property
    def image_shape(self) -> tuple[int, int]:
        """(h, w) of the field grid and of the stage's images."""
        return self.model.image_shape

    @property
    def envelope(self) -> bool:
        """Whether the stage uses the coarse envelope model."""
        return isinstance(self.model, EnvelopeModel)

    def stage_sources(self, sources_um: torch.Tensor) -> torch.Tensor:
        """Sources (B, 3) in the stage model's coordinates.

        The shift's tensor is made once per device and dtype: on CUDA a tensor made from Python numbers is a copy from
        host memory, and torch waits for the device's queue to drain before each such copy (twice an iteration).
        """
        key = (sources_um.device, sources_um.dtype)
        if key not in self._shift:
            self._shift[key] = torch.tensor([self.shift_um[0], self.shift_um[1], 0.0], device=sources_um.device, dtype=sources_um.dtype)
        return sources_um - self._shift[key]

    def to_field_grid(self, delta_n: torch.Tensor) -> torch.Tensor:
        """RI contrast on the stage grid (Z, h, w) → the field grid (Z, h_f, w_f), differentiable."""
        return upsample_to(delta_n, self.factor // self.field_factor, self.image_shape)


def _shift_um(n_full: int, g: int, dx: float) -> float:
    return ((g - 1) / 2 - (n_full // 2) + (n_full // g // 2) * g) * dx


def multislice_plan(
    optics: Optics,
    factor: int,
    full_shape: tuple[int, int],
    sources_um: np.ndarray,
    *,
    depth_slack_um: float = 2.0,
    offset_slack_um: float = 1.0,
) -> tuple[int, Optics, tuple[float, float], GridPlan]:
    """Field factor, stage optics, origin shift (x, y) µm and window of a multi-slice stage.

    The window is planned for the current sources plus some slack for the moves of calibration.
    """
    big_h, big_w = full_shape
    dx = optics.pixel_size_um
    g = field_factor(optics, factor)
    opt = stage_optics(optics, g)
    shift = (_shift_um(big_w, g, dx), _shift_um(big_h, g, dx))
    src = np.asarray(sources_um, dtype=np.float64)
    plan = plan_grid(
        opt, (big_h // g, big_w // g),
        (float(np.abs(src[:, 1] - shift[1]).max()) + offset_slack_um, float(np.abs(src[:, 0] - shift[0]).max()) + offset_slack_um),
        float(src[:, 2].max()) + depth_slack_um,
        warn=False,
    )
    return g, opt, shift, plan


#: The physics' criterion of the ``"auto"`` sub-slices part: it is tried only where a slice is at least this fraction of the
#: depth of field (:attr:`~napari_fdt.physics.optics.Optics.depth_of_field_um`); below, a thin screen's error, growing as
#: (slice / depth of field)², is under about a quarter of the 1-7 % measured at 0.84 and the part is not worth a trial.
SUB_SLICE_MIN_DOF_RATIO = 0.5


def thick_slices(optics: Optics) -> bool:
    """Whether the slices are thick enough against the depth of field for sub-slices to be worth trying
    (:data:`SUB_SLICE_MIN_DOF_RATIO`)."""
    return optics.slice_spacing_um / optics.depth_of_field_um >= SUB_SLICE_MIN_DOF_RATIO


def camera_grid_drops_band(optics: Optics) -> bool:
    """Whether the camera grid's Nyquist frequency ``1/(2·pixel_size_um)`` lies below the medium's ``n_b/λ`` (cycles/µm):
    waves scattered between the two are aliased on the camera grid, and the ``"auto"`` 2x field grid is worth trying."""
    return 0.5 / optics.pixel_size_um < optics.n_background / optics.wavelength_um


#: ``field_window = "auto"`` runs the split-field model where its window has at most this fraction of the full window's
#: pixels: on the suite 17-52 % (a step 1.4-2.8x faster on the CPU); on the authors' 512² demo geometry the light cone's
#: margin fills the full window (100 %), where the split model adds its source fields and their memory (7x the full
#: model's estimate at batch 16) for nothing.
SPLIT_MAX_FRACTION = 0.6


def split_window_fraction(plan: GridPlan, optics: Optics) -> float:
    """Pixels of the split model's window (:func:`~napari_fdt.model.split_field.split_plan`) over the full window's."""
    small = split_plan(plan, optics).padded_shape
    return (small[0] * small[1]) / (plan.padded_shape[0] * plan.padded_shape[1])


def uses_split_field(field_window: str, device_type: str, factor: int, window_fraction: float, *, field_oversampling: int = 1,
                     pupil_edge: float | None = None, pixel_integration: bool = False,
                     image_shape: tuple[int, int] = (0, 0)) -> bool:
    """Whether a multi-slice stage of ``factor`` runs the split-field model (:class:`~napari_fdt.model.split_field.SplitFieldModel`,
    on the 2x field grid :class:`~napari_fdt.model.oversampled.OversampledModel` with ``split``), for the
    setting ``field_window`` on a device of ``device_type`` ("cpu", "cuda") with :func:`split_window_fraction`
    ``window_fraction``: ``"split"``, or ``"auto"`` on the CPU where the fraction is at most :data:`SPLIT_MAX_FRACTION`;
    never where the stage needs what only the full window has (on the 2x grid, pixel means or an image of odd size) or
    the pupil's edge is narrower than the window's taper (a hard pupil's tails wrap
    on the small window: 0.25 % against 0.11 % image error on the sample, 1.3 % against 0.8 % on cells_pupil, both
    against a window twice as wide; docs/decisions/split-field.md)."""
    hard = pupil_edge is not None and pupil_edge < DEFAULT_PUPIL_TAPER
    fine_full = fine_field_grid(field_oversampling, factor) and (pixel_integration or any(n % 2 for n in image_shape))
    if hard or fine_full:
        return False
    if field_window == "auto":
        return device_type != "cuda" and window_fraction <= SPLIT_MAX_FRACTION
    return field_window == "split"


def model_window(plan: GridPlan, optics: Optics, split: bool) -> tuple[int, int]:
    """(h, w) of the window a multi-slice stage's FFTs run on: ``plan``'s, or the split model's (:func:`split_plan`)."""
    return tuple(split_plan(plan, optics).padded_shape) if split else tuple(plan.padded_shape)


def config_uses_split_field(config, device_type: str, factor: int, plan: GridPlan, optics: Optics,
                            pupil_edge: float | None, field_grid: bool = False, pixel_integration: bool = False) -> bool:
    """:func:`uses_split_field` for a solver configuration's stage of ``factor`` (its full window ``plan`` and stage
    ``optics``), as the plan and the memory check price it before the run (``field_grid``: the ``"auto"`` 2x field grid
    on; ``pixel_integration``: the camera's)."""
    return uses_split_field(config.field_window, device_type, factor, split_window_fraction(plan, optics),
                            field_oversampling=stage_field_oversampling(config.field_oversampling, field_grid),
                            pupil_edge=pupil_edge, pixel_integration=pixel_integration, image_shape=plan.image_shape)


def build_stage(
    index: int,
    factor: int,
    iterations: int,
    optics: Optics,
    images_normalised: torch.Tensor | LazyImages,
    sources_um: np.ndarray,
    *,
    device: torch.device,
    depth_slack_um: float = 2.0,
    offset_slack_um: float = 1.0,
    coarse_model: str = "envelope",
    backward_mode: str = "auto",
    obliquity: str = "none",
    pupil_edge: float | None = None,
    pixel_integration: bool = False,
    sub_slices: int = 1,
    field_oversampling: int = 1,
    field_window: str = "full",
) -> Stage:
    """Set up one stage for the current source estimates (the window gets some slack for calibration moves).

    ``coarse_model="envelope"`` uses :class:`~napari_fdt.model.envelope.EnvelopeModel` on the stage grid for
    factors > 1; ``"multislice"`` keeps the multi-slice model on the grid the pupil needs.
    ``backward_mode``, ``obliquity``, ``pupil_edge``, ``pixel_integration``, ``sub_slices``: see
    :class:`~napari_fdt.model.forward.MultiSliceModel` (multi-slice stages only; :func:`camera_model_options`).
    ``field_oversampling`` 2: a factor-1 stage runs :class:`~napari_fdt.model.oversampled.OversampledModel` (the field on
    a grid twice as fine; coarse stages keep their grids). ``field_window`` "split": :func:`uses_split_field`.
    """
    _, big_h, big_w = images_normalised.shape
    dx = optics.pixel_size_um
    if runs_envelope(factor, coarse_model):
        h, w = big_h // factor, big_w // factor
        shift = (_shift_um(big_w, factor, dx), _shift_um(big_h, factor, dx))
        env = EnvelopeModel(optics, (h, w), factor, (0.0, 0.0), device=device)
        imgs = stage_images(images_normalised, h, w, factor, device)
        stage = Stage(index, factor, factor, iterations, optics, env, imgs, shift, (h, w), env.padded)
        src = torch.as_tensor(np.asarray(sources_um), dtype=env.dtype, device=device)
        stage.coverage = env.coverage(stage.stage_sources(src))
        return stage
    g, opt, shift, plan = multislice_plan(optics, factor, (big_h, big_w), sources_um,
                                          depth_slack_um=depth_slack_um, offset_slack_um=offset_slack_um)
    h, w = plan.image_shape
    fine = fine_field_grid(field_oversampling, factor)
    model_class, options = (OversampledModel if fine else MultiSliceModel), {}
    if uses_split_field(field_window, torch.device(device).type, factor, split_window_fraction(plan, opt),
                        field_oversampling=field_oversampling, pupil_edge=pupil_edge, pixel_integration=pixel_integration,
                        image_shape=plan.image_shape):
        model_class, options = (OversampledModel, {"split": True}) if fine else (SplitFieldModel, {})
    model = model_class(opt, plan, device=device, backward_mode=backward_mode, obliquity=obliquity,
                        pupil_edge=pupil_edge, pixel_integration=pixel_integration, sub_slices=sub_slices, **options)
    imgs = stage_images(images_normalised, h, w, g, device)
    grid = (big_h // factor, big_w // factor)
    return Stage(index, factor, g, iterations, opt, model, imgs, shift, grid, model.plan.padded_shape)


def camera_model_options(config, acquisition) -> dict:
    """``pupil_edge`` and ``pixel_integration`` of the stage models for a solver configuration and an acquisition.

    ``config.pupil_edge`` None: ``acquisition.json``'s optional ``pupil_edge`` (default 0.03). ``pixel_integration``
    ``"auto"``: ``acquisition.json``'s optional ``pixel_integration`` if stated; a simulated folder without it was
    written before the camera model existed, with point samples (off); otherwise (a real camera) the physical rule
    :func:`napari_fdt.physics.camera.needs_pixel_integration`. Integration over the acquisition's pixels carries
    to coarse stages: the block average of pixel means is the mean over the larger pixel.
    """
    extra = getattr(acquisition, "extra", None) or {}
    edge = config.pupil_edge
    if edge is None:
        edge = extra.get("pupil_edge", DEFAULT_PUPIL_TAPER)
        if isinstance(edge, bool) or not isinstance(edge, (int, float)) or not (0.0 <= edge < 0.5):
            raise FDTInputError("pupil_edge", f"acquisition.json's pupil_edge must be a number in [0, 0.5), got {edge!r}",
                                "0 for a hard pupil, 0.03 the default soft edge, or remove the key")
        edge = float(edge)
    return {"pupil_edge": edge, "pixel_integration": resolved_pixel_integration(config, acquisition)}


def resolved_pixel_integration(config, acquisition) -> bool:
    """Pixel integration as stated (:func:`stated_pixel_integration`), else the physical rule
    (:func:`napari_fdt.physics.camera.needs_pixel_integration`: the intensity's band 2·NA/λ beyond the camera's Nyquist)."""
    from napari_fdt.physics.camera import needs_pixel_integration

    stated = stated_pixel_integration(config, acquisition)
    if stated is not None:
        return stated
    o = acquisition.optics
    return needs_pixel_integration(o.na, o.wavelength_um, o.pixel_size_um)


def camera_model(config, acquisition) -> CameraModel:
    """The run's :class:`~napari_fdt.recon.problem.stage_spec.CameraModel` (:func:`camera_model_options`), resolved once."""
    return CameraModel(**camera_model_options(config, acquisition))


def stated_pixel_integration(config, acquisition) -> bool | None:
    """Pixel integration as the setting or the acquisition states it; None when nothing does (``"auto"`` on a real
    camera's data without the key): the solver then applies the physical rule (:func:`~napari_fdt.recon.loop.model_parts.requested_for`).

    ``true``/``false``: as set; ``"auto"``: ``acquisition.json``'s ``pixel_integration`` if present, False for a
    simulated folder without it (written before the camera model existed, with point samples)."""
    from napari_fdt.physics.camera import resolve_pixel_integration

    extra = getattr(acquisition, "extra", None) or {}
    optics = acquisition.optics
    setting_ = config.pixel_integration
    if setting_ == "auto":
        if "pixel_integration" in extra:
            setting_ = extra["pixel_integration"]
        elif "simulated" in extra:
            return False
        else:
            return None
    return resolve_pixel_integration(setting_, optics.na, optics.wavelength_um, optics.pixel_size_um)
