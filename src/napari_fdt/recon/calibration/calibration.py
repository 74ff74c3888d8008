"""The self-calibration parameters of a reconstruction, with their optimiser and their state.

Besides the RI grid the solver fits (``docs/solver.md``): the lateral position of every source, a log-gain
per image, a common offset of the source plane's depth, and optionally the pixel size and the slice
spacing as global scales of the acquisition's values. :class:`Calibration` holds them as tensors on the
solver's device, switches them on per stage, and keeps one Adam optimiser for them over the whole run.
Lengths in µm; gains in the solver's normalised image units (images divided by the acquisition's mean).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from napari_fdt.physics.aberrations import ZERNIKE_MODES
from napari_fdt.physics.optics import Optics
from napari_fdt.recon.calibration.adam import Adam
from napari_fdt.recon.settings.config import SolverConfig

__all__ = ["Calibration"]

#: The tensors of :class:`Calibration`, in the order of its state dict (and of the checkpoint's keys).
PARAMETERS = ("sources", "log_gain", "pixel_scale", "spacing_scale", "depth_offset_um", "na_scale", "pupil_edge", "zernike")
#: The pupil parts' parameters (NA scale, edge, Zernike phase): what a kept part starts from when stages run again.
PUPIL_PARAMETERS = ("na_scale", "pupil_edge", "zernike")
#: Smallest calibrated pupil edge (relative to NA/λ): a hard edge has no gradient in NA.
MIN_CALIBRATED_EDGE = 0.002


class Calibration:
    """Per-source positions and gains, and the global optical scales, as optimised parameters.

    Parameters
    ----------
    sources_um: (N, 3) start positions [x, y, depth] (acquisition coordinates).
    config: the solver settings (``calibrate_*`` switches, ``calibration_from_stage``, ``lr_*`` rates).
    optics: the acquisition's optics (the scales multiply its pixel size and slice spacing).
    device, dtype: of the tensors.

    Tensors: ``sources`` (N, 3) µm, ``log_gain`` (N,), ``pixel_scale`` and ``spacing_scale`` () (1 = the
    acquisition's value), ``depth_offset_um`` () µm added to every source's depth; the pupil's ``na_scale`` () and
    ``pupil_edge`` () (``calibrate_pupil``; the edge used is ``|pupil_edge|``, started at least at
    :data:`MIN_CALIBRATED_EDGE`) and the Zernike coefficients ``zernike`` (6,) radians
    (``calibrate_aberrations``; :data:`napari_fdt.physics.aberrations.ZERNIKE_MODES`).
    """

    def __init__(self, sources_um: np.ndarray, config: SolverConfig, optics: Optics, *, device: torch.device,
                 dtype: torch.dtype, pupil_edge: float = 0.03) -> None:
        self.config = config
        self.optics = optics
        n = len(sources_um)
        self.sources = torch.tensor(np.asarray(sources_um, dtype=np.float64), device=device, dtype=dtype)
        self.log_gain = torch.zeros(n, device=device, dtype=dtype)
        self.pixel_scale = torch.ones((), device=device, dtype=dtype)
        self.spacing_scale = torch.ones((), device=device, dtype=dtype)
        self.depth_offset_um = torch.zeros((), device=device, dtype=dtype)
        self.na_scale = torch.ones((), device=device, dtype=dtype)
        self.pupil_edge = torch.tensor(max(float(pupil_edge), MIN_CALIBRATED_EDGE), device=device, dtype=dtype)
        self.zernike = torch.zeros(len(ZERNIKE_MODES), device=device, dtype=dtype)
        #: whether the pupil's NA and edge, and the Zernike coefficients, are in the model (and trained from
        #: ``calibration_from_stage``): ``calibrate_pupil`` / ``calibrate_aberrations`` when true, else off until the
        #: solver's choice of model parts (:mod:`napari_fdt.recon.loop.model_parts`) switches them on
        self.fit_pupil = config.calibrate_pupil in (True, "true")
        self.fit_aberrations = config.calibrate_aberrations in (True, "true")
        #: stages (indices) whose positions and depth offset stay fixed: with ``calibrate_sources_in_envelope_stages`` off,
        #: the envelope stages before a multi-slice one (set by the solver)
        self.position_frozen_stages: frozenset[int] = frozenset()
        #: stages (indices) whose source depths (each source's own and the common offset) stay fixed while x, y train:
        #: with ``calibrate_source_depth_in_envelope_stages`` off, the envelope stages before a multi-slice one (set by the solver)
        self.depth_frozen_stages: frozenset[int] = frozenset()
        #: stages (indices) that run the envelope model: their position steps keep scale 1, the other stages'
        #: are ``multislice_source_step_scale`` times longer (set by the solver)
        self.envelope_stages: frozenset[int] = frozenset()
        self._depth_frozen = False
        #: the stage the optimiser's moments belong to (:meth:`set_trainable`; ``restart_source_moments``)
        self._moments_stage: int | None = None
        #: whether the gains hold their least-squares start (:meth:`set_gains`)
        self.gain_initialised = False
        #: one Adam for the whole run, built by the first :meth:`set_trainable`
        self.optimiser: CalibrationOptimiser | None = None

    # -- values --------------------------------------------------------------------------------
    def calibrated_sources(self, shared_frozen: bool = False) -> torch.Tensor:
        """(N, 3) positions with the common depth offset applied (acquisition coordinates, µm), differentiable.

        ``shared_frozen``: the offset enters as a constant (held-out images' gradients reach their own rows only).
        """
        d = self.depth_offset_um.detach() if shared_frozen or self._depth_frozen else self.depth_offset_um
        offset = torch.stack([torch.zeros_like(d), torch.zeros_like(d), d])
        sources = self.sources
        if self._depth_frozen and sources.requires_grad:  # x, y train; each source's own depth is a constant
            sources = torch.cat([sources[:, :2], sources[:, 2:].detach()], dim=1)
        return sources + offset

    def sources_um(self) -> np.ndarray:
        """(N, 3) calibrated positions as float64 numpy (µm, acquisition coordinates)."""
        return self.calibrated_sources().detach().cpu().double().numpy()

    def gains(self) -> np.ndarray:
        """(N,) gains ``exp(log_gain)`` as float64 numpy (normalised image units per model unit)."""
        return torch.exp(self.log_gain.detach()).cpu().double().numpy()

    def summary(self) -> dict[str, float]:
        """The calibrated global parameters: pixel size and slice spacing (µm), depth offset of the sources (µm)."""
        optics = self.optics
        return {
            "pixel_size_um": optics.pixel_size_um * float(self.pixel_scale.detach()),
            "slice_spacing_um": optics.slice_spacing_um * float(self.spacing_scale.detach()),
            "source_depth_offset_um": float(self.depth_offset_um.detach()),
            **({"na": optics.na * float(self.na_scale.detach()), "pupil_edge": abs(float(self.pupil_edge.detach()))}
               if self.fit_pupil else {}),
            **({f"aberration_{m}_rad": float(v) for m, v in zip(ZERNIKE_MODES, self.zernike.detach().cpu().tolist())}
               if self.fit_aberrations else {}),
        }

    def optics_overrides(self, stage_optics: Optics, envelope: bool, shared_frozen: bool = False) -> dict[str, torch.Tensor]:
        """Keyword overrides of a stage model's optics for the calibrated scales (see :class:`~napari_fdt.model.protocol.ImageModel`).

        The envelope model's pixel is tied to its stage grid, so it gets no pixel-size override. ``shared_frozen``:
        the scales enter as constants.
        """
        cfg = self.config
        pixel, spacing = (self.pixel_scale.detach(), self.spacing_scale.detach()) if shared_frozen else (self.pixel_scale, self.spacing_scale)
        out = {}
        if cfg.calibrate_pixel_size and not envelope:
            out["pixel_size_um"] = stage_optics.pixel_size_um * pixel
        if cfg.calibrate_slice_spacing:
            out["slice_spacing_um"] = stage_optics.slice_spacing_um * spacing
        if not envelope:  # the envelope model keeps the acquisition's pupil
            if self.fit_pupil:
                na_scale, edge = (self.na_scale.detach(), self.pupil_edge.detach()) if shared_frozen else (self.na_scale, self.pupil_edge)
                out["na"] = stage_optics.na * na_scale
                out["pupil_edge"] = torch.abs(edge)
            if self.fit_aberrations:
                out["zernike"] = self.zernike.detach() if shared_frozen else self.zernike
        return out

    def set_gains(self, gains: torch.Tensor) -> None:
        """Start the gains at ``gains`` (N,) (> 0), e.g. least-squares fits to the homogeneous medium."""
        with torch.no_grad():
            self.log_gain.copy_(torch.log(gains))
        self.gain_initialised = True

    # -- optimisation --------------------------------------------------------------------------
    def set_trainable(self, stage_index: int) -> None:
        """Switch each parameter's gradient on or off for stage ``stage_index``; build the optimiser on first use.

        Positions, depth offset and global scales train from ``calibration_from_stage`` on (each if its
        ``calibrate_*`` switch is on), the positions and the depth offset not in :attr:`position_frozen_stages`;
        the gains in every stage if ``calibrate_gain``.
        """
        cfg = self.config
        on = stage_index >= cfg.calibration_from_stage
        positions = on and stage_index not in self.position_frozen_stages
        self._depth_frozen = stage_index in self.depth_frozen_stages
        self.sources.requires_grad_(positions and cfg.calibrate_sources)
        self.depth_offset_um.requires_grad_(positions and cfg.calibrate_source_depth and not self._depth_frozen)
        self.pixel_scale.requires_grad_(on and cfg.calibrate_pixel_size)
        self.spacing_scale.requires_grad_(on and cfg.calibrate_slice_spacing)
        self.na_scale.requires_grad_(on and self.fit_pupil)
        self.pupil_edge.requires_grad_(on and self.fit_pupil)
        self.zernike.requires_grad_(on and self.fit_aberrations)
        self.log_gain.requires_grad_(cfg.calibrate_gain)
        if self.optimiser is None:
            self.optimiser = CalibrationOptimiser(self.sources, [
                {"params": [self.log_gain], "lr": cfg.lr_log_gain},
                {"params": [self.pixel_scale, self.spacing_scale], "lr": cfg.lr_global},
                {"params": [self.depth_offset_um], "lr": cfg.lr_depth_offset_um},
                {"params": [self.na_scale, self.pupil_edge], "lr": cfg.lr_pupil},
                {"params": [self.zernike], "lr": cfg.lr_aberrations},
            ], config=cfg)
        if cfg.restart_source_moments and self._moments_stage is not None and stage_index != self._moments_stage:
            self.optimiser.restart_positions(self.sources, self.depth_offset_um)
        self._moments_stage = stage_index
        envelope = stage_index in self.envelope_stages
        interval = len(self.sources) / cfg.stage_batch(stage_index)
        self.optimiser.set_visit_interval(interval, self.max_visit_step_um(), 1.0 if envelope else cfg.multislice_source_step_scale)
        if self.optimiser.rows is not None:
            cosine = cfg.source_step_schedule == "cosine" and not envelope
            group = self.optimiser.rows.param_groups[0]
            group["cosine_visits"] = max(1.0, cfg.stages[stage_index].iterations / max(1.0, interval)) if cosine else None
            visits = self.optimiser.rows.state.get(self.sources, {}).get("visits")  # none after a restart
            group["cosine_from"] = visits[:, None].clone() if cosine and visits is not None else 0.0

    def max_visit_step_um(self) -> float:
        """Largest step of a source per visit, µm: ``λ / (4·NA)``, a quarter of the lateral resolution. A shift by
        half the resolution turns a fringe of the source's image from bright to dark, so the loss of one image
        is smooth in its position only over about this distance and a longer step overshoots."""
        return self.optics.wavelength_um / (4.0 * self.optics.na)

    def shared_parameters(self) -> list[torch.Tensor]:
        """The parameters every image's gradient reaches (summed over ranks in a distributed run)."""
        return [self.pixel_scale, self.spacing_scale, self.depth_offset_um, self.na_scale, self.pupil_edge, self.zernike]

    def per_source_parameters(self) -> list[torch.Tensor]:
        """The parameters with one row per image (each row's gradient comes from its own image only)."""
        return [self.sources, self.log_gain]

    def per_source_rows(self, optimiser_state: bool = False) -> list[torch.Tensor | None]:
        """The per-image tensors, and with ``optimiser_state`` their Adam moments (None where not yet made)."""
        tensors: list[torch.Tensor | None] = list(self.per_source_parameters())
        if optimiser_state and self.optimiser is not None:
            if self.optimiser.rows is not None:  # (made where no row was visited yet: every rank shares the same tensors)
                for p in self.optimiser.rows.param_groups[0]["params"]:
                    self.optimiser.rows.ensure_state(p)
            for p in self.per_source_parameters():
                state = self.optimiser.state.get(p, {})
                tensors += [state.get(k) for k in ("exp_avg", "exp_avg_sq", "visits")]
        return tensors

    # -- state ---------------------------------------------------------------------------------
    def copy_values(self, names: tuple[str, ...] = PARAMETERS) -> dict[str, torch.Tensor]:
        """Copies of the tensors ``names`` (default all; :data:`PUPIL_PARAMETERS`: the pupil parts' fitted values) on
        their device, for :meth:`restore_values` after a cancel or a restart."""
        return {name: getattr(self, name).detach().clone() for name in names}

    def restore_values(self, values: dict[str, torch.Tensor]) -> None:
        """Set the tensors in place from :meth:`copy_values` or :meth:`state_dict` (a checkpoint without the pupil's
        and aberrations' tensors, from an earlier version, keeps their start values)."""
        with torch.no_grad():
            for name in PARAMETERS:
                if name in values:
                    getattr(self, name).copy_(values[name])

    def state_dict(self) -> dict[str, Any]:
        """The tensors (on the CPU), whether the gains were initialised (``gain_initialised``) and the optimiser's state (``cal_opt``)."""
        state: dict[str, Any] = {name: getattr(self, name).detach().cpu() for name in PARAMETERS}
        state["gain_initialised"] = self.gain_initialised
        state["cal_opt"] = None if self.optimiser is None else self.optimiser.state_dict()
        return state

    def load_state_dict(self, state: dict[str, Any], stage_index: int) -> None:
        """Restore :meth:`state_dict`; ``stage_index`` is the stage whose trainable switches the optimiser state belongs to."""
        self.restore_values(state)
        self.gain_initialised = bool(state["gain_initialised"])
        if state["cal_opt"] is not None:
            self.set_trainable(stage_index)
            self.optimiser.load_state_dict(state["cal_opt"])


class RowAdam(torch.optim.Optimizer):
    """Adam for per-image rows (first axis = image) that steps a row only when its image was in the batch.

    A row is visited when its gradient row is non-zero; its moments and its step count advance only then
    (lazy Adam), so one visit moves it by about ``lr`` (bias-corrected Adam), wherever the visits fall.

    ``moment`` (the second moment that scales the step):

    - ``"isotropic"``: the row's mean square over its columns: the step follows the gradient's direction in µm.
    - ``"matrix"``: the row's (C, C) mean outer product ``E[g·gᵀ]``; the step is ``lr·(V + δ·tr(V)/C·I)^(-1/2)·m``
      (full-matrix Adam per row, δ = ``damping``). It whitens the coupled directions of a row: the depth and the
      lateral position of a deep source off the field's axis move its image almost alike (the valley along the
      ray to the field), where a scalar or diagonal scale steps across the valley and barely along it.

    ``max_step``: a step longer than this (in the row's units) is shortened to it (None: no limit).
    """

    def __init__(self, params: list[torch.Tensor], lr: float, betas: tuple[float, float] = (0.9, 0.99), eps: float = 1e-8,
                 moment: str = "isotropic", damping: float = 0.01, max_step: float | None = None) -> None:
        if moment not in ("isotropic", "matrix"):
            raise ValueError(f"moment must be 'isotropic' or 'matrix', got {moment!r}")
        super().__init__(params, {"lr": lr, "betas": betas, "eps": eps, "moment": moment, "damping": damping, "max_step": max_step,
                                  "cosine_visits": None, "cosine_from": 0.0})

    def ensure_state(self, p: torch.Tensor) -> dict[str, torch.Tensor]:
        """The state of ``p``, made (zero moments, no visits: what the first visit starts from) where not yet made. A
        distributed run makes it on every rank before sharing it, so that a rank none of whose rows was visited yet
        takes part with the same tensors as the others."""
        st = self.state[p]
        if not st:
            rows = p.shape[0]
            cols = p.reshape(rows, -1).shape[1]
            matrix = self.param_groups[0]["moment"] == "matrix"
            st["exp_avg"] = torch.zeros((rows, cols), dtype=p.dtype, device=p.device)
            st["exp_avg_sq"] = torch.zeros((rows, cols, cols) if matrix else (rows, 1), dtype=p.dtype, device=p.device)
            st["visits"] = torch.zeros(rows, dtype=p.dtype, device=p.device)
        return st

    #: None: the step without device synchronisation on CUDA (:meth:`_masked_step`), the rows' own step elsewhere.
    #: True or False forces one (tests compare them).
    sync_free: bool | None = None

    @torch.no_grad()
    def step(self, closure=None):  # noqa: D102 (torch's signature)
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                sync_free = p.is_cuda if self.sync_free is None else self.sync_free
                (self._masked_step if sync_free else self._row_step)(group, p)
        return None

    def _row_step(self, group: dict, p: torch.Tensor) -> None:
        """Step the rows with a gradient, taken as indices (one device sync, ``nonzero``; and ``eigh``'s)."""
        g = p.grad.reshape(p.shape[0], -1)
        rows = (g != 0).any(dim=1).nonzero().squeeze(1)
        if rows.numel() == 0:
            return
        st = self.ensure_state(p)
        m, v, t = st["exp_avg"], st["exp_avg_sq"], st["visits"]
        b1, b2 = group["betas"]
        gr = g[rows]
        sq = self._second_moment(group, gr)
        m[rows] = b1 * m[rows] + (1 - b1) * gr
        v[rows] = b2 * v[rows] + (1 - b2) * sq
        t[rows] += 1
        start = group.get("cosine_from", 0.0)
        step = self._steps(group, m[rows], v[rows], t[rows, None], start[rows] if torch.is_tensor(start) else start, g.dtype, False)
        p.view(p.shape[0], -1)[rows] -= step

    def _masked_step(self, group: dict, p: torch.Tensor) -> None:
        """The same step over every row, rows without a gradient masked out: no host synchronisation (a GPU iteration
        runs ahead of its kernels only without one; ``nonzero`` and ``eigh`` each waited for the queue, 5.7 of 22 ms
        of the demo's step on an H200). The visited rows get the values of :meth:`_row_step` (``tests/test_source_steps.py``)."""
        g = p.grad.reshape(p.shape[0], -1)
        st = self.ensure_state(p)
        m, v, t = st["exp_avg"], st["exp_avg_sq"], st["visits"]
        b1, b2 = group["betas"]
        visited = (g != 0).any(dim=1)
        sq = self._second_moment(group, g)
        vis = visited.reshape(-1, *([1] * (sq.ndim - 1)))
        m.copy_(torch.where(visited[:, None], b1 * m + (1 - b1) * g, m))
        v.copy_(torch.where(vis, b2 * v + (1 - b2) * sq, v))
        t.add_(visited.to(t.dtype))
        step = self._steps(group, m, v, t.clamp_min(1)[:, None], group.get("cosine_from", 0.0), g.dtype, True)
        p.view(p.shape[0], -1).sub_(torch.where(visited[:, None], step, torch.zeros_like(step)))

    @staticmethod
    def _second_moment(group: dict, g: torch.Tensor) -> torch.Tensor:
        """This visit's second moment of gradient rows ``g`` (R, C): their outer products (R, C, C) for the ``"matrix"``
        moment, their mean squares (R, 1) for the ``"isotropic"`` one."""
        return g[:, :, None] * g[:, None, :] if group["moment"] == "matrix" else g.square().mean(dim=1, keepdim=True)

    @staticmethod
    def _steps(group: dict, m: torch.Tensor, v: torch.Tensor, tr: torch.Tensor, start, dtype: torch.dtype,
               sync_free: bool) -> torch.Tensor:
        """The steps (R, C) of rows with moments ``m`` (R, C), ``v`` and visits ``tr`` (R, 1), this visit counted."""
        b1, b2 = group["betas"]
        m_hat = m / (1 - b1 ** tr)
        if group["moment"] == "matrix":
            v_hat = (v / (1 - b2 ** tr)[:, :, None]).double()
            if sync_free and group["damping"] > 0:
                # V̂ + δ·tr(V̂)/C·I (+ε²) is what the eigenvalues' form below builds (V̂ is positive semi-definite)
                c = v_hat.shape[-1]
                shift = group["damping"] * torch.diagonal(v_hat, dim1=-2, dim2=-1).sum(-1) / c + group["eps"] ** 2
                damped = v_hat + shift[:, None, None] * torch.eye(c, dtype=v_hat.dtype, device=v_hat.device)
                inv_sqrt = inverse_sqrt_spd(damped, condition_bound=c / group["damping"])
            else:
                lam, q = torch.linalg.eigh(v_hat)
                lam = lam.clamp_min(0) + group["damping"] * lam.clamp_min(0).mean(dim=1, keepdim=True) + group["eps"] ** 2
                inv_sqrt = (q * lam.rsqrt()[:, None, :]) @ q.transpose(1, 2)
            step = group["lr"] * (inv_sqrt @ m_hat.double()[:, :, None])[:, :, 0].to(dtype)
        else:
            step = group["lr"] * m_hat / ((v / (1 - b2 ** tr)).sqrt() + group["eps"])
        if group["max_step"] is not None:
            norm = step.norm(dim=1, keepdim=True)
            step = step * (group["max_step"] / norm.clamp_min(group["max_step"])).clamp(max=1.0)
        if group.get("cosine_visits"):  # ½(1 + cos(π·v/V)), v = the row's visits in this stage before this one
            u = ((tr - 1 - start) / group["cosine_visits"]).clamp(0.0, 1.0)
            step = step * (0.5 * (1.0 + torch.cos(torch.pi * u))).to(step.dtype)
        return step


def inverse_sqrt_spd(a: torch.Tensor, condition_bound: float) -> torch.Tensor:
    """``A^(-1/2)`` of symmetric positive definite matrices (..., C, C) whose condition number is at most
    ``condition_bound``, by the coupled Newton–Schulz iteration, with no host synchronisation (``torch.linalg.eigh``
    waits for the GPU to check its convergence).

    ``A`` is scaled by its Frobenius norm, so its eigenvalues lie in [1/(κ·√C), 1]; the iteration count is fixed from
    that bound (each iteration multiplies a small eigenvalue's progress by about 2.25, then converges quadratically):
    float64 round-off for κ ≤ 10⁴. Checked against ``eigh`` in ``tests/test_source_steps.py``.
    """
    c = a.shape[-1]
    norm = a.square().sum(dim=(-2, -1), keepdim=True).sqrt()
    smallest = 1.0 / (float(condition_bound) * math.sqrt(c))
    iterations = int(math.ceil(math.log(1.0 / smallest) / math.log(2.25))) + 7
    eye = torch.eye(c, dtype=a.dtype, device=a.device).expand_as(a).reshape(-1, c, c)
    y = (a / norm).reshape(-1, c, c)
    z, three_halves = eye, 1.5 * eye
    for _ in range(iterations):  # three batched products per iteration (on a GPU each operation is a kernel launch)
        t = torch.baddbmm(three_halves, z, y, alpha=-0.5)
        y, z = torch.bmm(y, t), torch.bmm(t, z)
    return z.reshape(a.shape) / norm.sqrt()


class CalibrationOptimiser:
    """The calibration's optimiser: torch's Adam for the gains, global scales and depth offset, and for the
    source positions either :class:`RowAdam` (``source_step`` ``"per_visit"``) or the same Adam (``"dense"``).

    ``"per_visit"``: a row's step per visit is ``min(lr_sources_um × N / B, λ / (4·NA))`` (:meth:`set_visit_interval`):
    a row is in one batch of every ``N / B``, so it moves on average ``lr_sources_um`` per iteration, as a dense
    parameter would, whatever the number of images, up to the step that one image's loss still resolves
    (:meth:`Calibration.max_visit_step_um`); multi-slice stages multiply both by ``multislice_source_step_scale``.
    Dense Adam on rows that see a gradient once per ``K`` iterations moves
    them about ``lr·√K`` per visit, ``lr/√K`` per iteration: slower the more images there are.
    """

    def __init__(self, sources: torch.Tensor, groups: list[dict], config: SolverConfig) -> None:
        self.config = config
        if config.source_step == "dense":
            groups = [{"params": [sources], "lr": config.lr_sources_um}, *groups]
            self.rows: RowAdam | None = None
        else:
            self.rows = RowAdam([sources], lr=config.lr_sources_um, betas=(0.9, 0.99),
                                moment="matrix" if config.source_step == "whitened" else "isotropic")
        self.adam = Adam(groups, betas=(0.9, 0.99))

    def set_visit_interval(self, interval: float, max_step_um: float, scale: float = 1.0) -> None:
        """Set the rows' step per visit from the iterations between two visits (``N / B``, at least 1), at most
        ``max_step_um``; ``scale`` multiplies both (``multislice_source_step_scale`` in multi-slice stages)."""
        if self.rows is not None:
            self.rows.param_groups[0]["lr"] = scale * min(self.config.lr_sources_um * max(1.0, float(interval)), max_step_um)
            self.rows.param_groups[0]["max_step"] = scale * max_step_um

    def restart_positions(self, sources: torch.Tensor, depth_offset: torch.Tensor) -> None:
        """Forget the moments (and the rows' visit counts) of the positions and the depth offset: their next step is a
        first Adam step again, of the full per-visit length, along the new stage's gradient only."""
        for opt in (self.adam, self.rows):
            if opt is not None:
                opt.state.pop(sources, None)
                opt.state.pop(depth_offset, None)  # torch's Adam keeps its step count in the state: popped too

    @property
    def state(self) -> dict:
        """Per-parameter optimiser state (moments; ``visits`` for the rows), keyed by tensor."""
        st = dict(self.adam.state)
        if self.rows is not None:
            st.update(self.rows.state)
        return st

    def zero_grad(self, set_to_none: bool = True) -> None:
        self.adam.zero_grad(set_to_none=set_to_none)
        if self.rows is not None:
            self.rows.zero_grad(set_to_none=set_to_none)

    def step(self) -> None:
        self.adam.step()
        if self.rows is not None:
            self.rows.step()

    def state_dict(self) -> dict:
        """``{"adam": …, "rows": … or None}``."""
        return {"adam": self.adam.state_dict(), "rows": None if self.rows is None else self.rows.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` (a checkpoint of the same ``source_step``).

        A checkpoint written before the rows had their own optimiser holds one Adam whose first group is the
        positions: with ``"dense"`` it loads as it is; otherwise the positions' moments start afresh."""
        if "adam" not in state:  # torch's Adam state dict of the older checkpoints
            if self.rows is None:
                self.adam.load_state_dict(state)
                return
            first = set(state["param_groups"][0]["params"])
            state = {"adam": {"state": {k: v for k, v in state["state"].items() if k not in first},
                              "param_groups": state["param_groups"][1:]}, "rows": None}
        self.adam.load_state_dict(state["adam"])
        if self.rows is not None and state.get("rows") is not None:
            self.rows.load_state_dict(state["rows"])
