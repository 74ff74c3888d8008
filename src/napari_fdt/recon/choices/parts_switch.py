"""The switches of the optional model parts in a run (:mod:`napari_fdt.recon.loop.model_parts`): each part's state before
any choice, a choice applied (made in the run or read from a checkpoint), and the restart of every stage with the parts
a first choice kept. How "auto" parts are chosen is :mod:`napari_fdt.recon.choices.parts_search`'s.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from napari_fdt.model.coherence import emission_spectrum
from napari_fdt.recon.calibration.calibration import PUPIL_PARAMETERS
from napari_fdt.recon.loop.model_parts import PARTS, PartsChoice, requested_for
from napari_fdt.recon.loop.parts_price import finest_end_test_s, finest_test_setup, part_costs
from napari_fdt.recon.loop.phases import RERUN
from napari_fdt.recon.problem.stage_roles import set_stage_roles
from napari_fdt.recon.problem.stage_spec import rerun_coarse_model

if TYPE_CHECKING:
    from napari_fdt.recon.loop.interface import Run

__all__ = ["init_parts", "drop_parts_that_do_not_fit", "set_parts", "parts_chosen_by", "apply_parts_choice", "restart_with_parts", "finest_again_with_parts",
           "tests_again_s"]




def init_parts(rec: Run) -> None:
    """Each part's switch before any choice: as set or stated, "auto" ones off; with nothing to choose (or no
    validation split to choose by) ``rec.parts_choice`` is made at once."""
    cfg = rec.config
    requested, chosen_by = requested_for(cfg, rec.acquisition, rec.coarse_model)
    #: the parts chosen from the data
    rec._auto_parts = [p for p in PARTS if requested[p] is None]
    parts = {p: bool(requested[p]) for p in PARTS}
    if not rec._auto_parts:
        rec.apply_parts_choice(PartsChoice(parts, chosen_by))
    elif not len(rec.validation_indices):
        for p in rec._auto_parts:
            chosen_by[p] = "no validation split"
        rec.apply_parts_choice(PartsChoice(parts, chosen_by))
    else:
        set_parts(rec, parts)
    rec._parts_chosen_by = chosen_by


def drop_parts_that_do_not_fit(rec: Run, sources_um) -> None:
    """The ``"auto"`` sub-slices and 2x field grid are not tried where the finest stage would not fit in the device's
    memory with them (the grid checked with the sub-slices it may run with; ``sources_um`` (N, 3) µm set the window);
    called after the check of the model the first pass runs, so that a part that might be kept never refuses a run that
    fits without it."""
    import dataclasses

    from napari_fdt.recon.problem.preflight import finest_stage_fits
    from napari_fdt.recon.problem.stage_spec import AUTO_SUB_SLICES

    if rec.parts_choice is not None:
        return
    n_wavelengths = len(rec.wavelengths) if rec.wavelengths else 1
    sub = AUTO_SUB_SLICES if "sub_slices" in rec._auto_parts else rec.config.sub_slices
    for part, changes, what in (("sub_slices", {"sub_slices": AUTO_SUB_SLICES}, f"{AUTO_SUB_SLICES} screens per slice"),
                                ("field_grid", {"field_oversampling": 2, "sub_slices": sub}, "the 2x field grid")):
        if part not in rec._auto_parts:
            continue
        fits, gib = finest_stage_fits(rec.acquisition, dataclasses.replace(rec.config, **changes), sources_um, rec.device, n_wavelengths)
        if not fits:
            rec._auto_parts = [p for p in rec._auto_parts if p != part]
            rec._parts_chosen_by[part] = f"memory: {what} would need about {gib:.1f} GiB"
    if not rec._auto_parts:
        rec.apply_parts_choice(PartsChoice(dict(rec.parts), dict(rec._parts_chosen_by)))


def parts_chosen_by(rec: Run, auto: str = "validation") -> dict[str, str]:
    """Per part what decided its switch, for a :class:`PartsChoice`: ``auto`` for the ``"auto"`` parts (tried by the
    held-out images), what decided the others (a setting, the acquisition, memory) as :func:`init_parts` recorded it."""
    return {p: (auto if p in rec._auto_parts else rec._parts_chosen_by[p]) for p in PARTS}


def set_parts(rec: Run, parts: dict[str, bool]) -> None:
    """Switch the parts: the spectral model's wavelengths and the calibration's pupil and aberration fits (the stage
    models take ``rec.parts`` when built)."""
    rec.parts = dict(parts)
    o, cfg = rec.acquisition.optics, rec.config
    if parts["spectral"]:
        lams, ws = emission_spectrum(o.wavelength_um, cfg.bandwidth_um, cfg.n_wavelengths)
        rec.wavelengths, rec.weights = list(map(float, lams)), list(map(float, ws))
    else:
        rec.wavelengths, rec.weights = None, None
    rec.calibration.fit_pupil = parts["pupil"]
    rec.calibration.fit_aberrations = parts["aberrations"]


def apply_parts_choice(rec: Run, choice: PartsChoice) -> None:
    """Take a choice of parts (made here, or read from a checkpoint): switches, and the fitted pupil values when the
    calibration has not moved them yet. A choice whose stages run again (``rerun`` ``"stages"``) also sets the coarse
    model they run with and the parts still to choose in the finest stage."""
    rec.parts_choice = choice
    set_parts(rec, choice.parts)
    if choice.rerun in ("stages", "before"):
        use_rerun_coarse_model(rec)
    if choice.rerun in ("stages", "finest", "before"):
        rec._choose_again = list(choice.pending)
        if choice.pending:
            rec._auto_parts = list(choice.pending)
        rec._parts_chosen_by = dict(choice.chosen_by)


def use_rerun_coarse_model(rec: Run) -> None:
    """The coarse stages of a run that holds the kept parts: multi-slice when ``coarse_model`` is ``"auto"`` (the
    envelope model holds none of the parts; a coarse model given by name is kept)."""
    rec.coarse_model = rerun_coarse_model(rec.config.coarse_model, rec.coarse_model)
    set_stage_roles(rec.calibration, rec.config, rec.coarse_model)


def restart_with_parts(rec: Run) -> None:
    """After a first choice that kept parts (``parts_rerun`` ``"stages"``): back to the state before any stage, with
    the kept parts on from the first stage (their parameters start from the fitted values and train from
    ``calibration_from_stage`` on) and the coarse stages multi-slice; the finest stage chooses the other auto parts
    again (now on top of the kept ones, through a volume trained with them)."""
    _mark_rerun(rec, "stages")
    fitted = rec.calibration.copy_values(PUPIL_PARAMETERS)
    rec._restart()
    rec.calibration.restore_values(fitted)  # the kept parts start from their fitted values


def finest_again_with_parts(rec: Run) -> None:
    """After a first choice that kept only parts of the finest stage's model (sub-slices): the finest stage runs again
    from its start with them (the caller restores its start), and the auto parts not kept are tried again at its end,
    through a volume trained with the kept ones (``rerun`` ``"finest"``, ``pending`` those parts)."""
    _mark_rerun(rec, "finest")


def _mark_rerun(rec: Run, rerun: str) -> None:
    """The choice made as the first pass's (its trials marked pass 1), with what runs again (``rerun``) and the auto
    parts not kept still to choose (``pending``); applied."""
    choice = rec.parts_choice
    for t in choice.trials:
        t.setdefault("pass", 1)
    choice.rerun = rerun
    choice.pending = [p for p in rec._auto_parts if not rec.parts[p]]
    rec.apply_parts_choice(choice)


def tests_again_s(rec: Run, kept: tuple[str, ...]) -> float:
    """Seconds of the tests at the end of the finest stage run again with the ``kept`` parts: the parts still to choose
    (``rec._auto_parts``) tried through the kept parts' model, as
    :func:`~napari_fdt.recon.loop.parts_price.finest_end_test_s` prices the first pass's. (Before, the first pass's
    price scaled by the two models' step costs: cells_fine 21.2 s priced against 3.1 s measured, since only the parts
    still to choose are tested again.)"""
    cfg = rec.config
    last = len(cfg.stages) - 1
    batch = cfg.stage_batch(last)

    def image_s(parts: tuple[str, ...]) -> float:
        return rec._stage_phase(last, RERUN, tuple(kept) + parts).seconds_per_iteration / batch

    remaining = tuple(rec._auto_parts)
    n_held = len(rec.validation_indices)
    n_test, n_fit, branch = finest_test_setup(cfg, rec.acquisition.n_images, n_held)
    # (the 2x grid priced as tried: where it waits for a spectral model's trial, that trial passed on beads_high and
    # fibres_thick's reruns, and the grid's test and branch were most of their tests there)
    return finest_end_test_s(part_costs(image_s(()), image_s, remaining), remaining, n_test, n_fit, n_held,
                             "cuda" if rec.device.type == "cuda" else "cpu", branch)
