"""One stage's loop and the run's state: :class:`~napari_fdt.recon.loop.interface.Run` (what helpers and choices may
touch of a run), :mod:`~napari_fdt.recon.loop.stage_loop` (a stage's iterations and the choices around them, their
:class:`~napari_fdt.recon.loop.stage_loop.Verdict`), :mod:`~napari_fdt.recon.loop.run_state`,
:mod:`~napari_fdt.recon.loop.snapshot`, :mod:`~napari_fdt.recon.loop.run_validation` (the held-out error during a run,
early stopping), :mod:`~napari_fdt.recon.loop.checkpoint`, :mod:`~napari_fdt.recon.loop.plan` and
:mod:`~napari_fdt.recon.loop.phases` (the run's phases and their predicted seconds), and the records and rules of
the choices: :mod:`~napari_fdt.recon.loop.regularisation` (TV weights), :mod:`~napari_fdt.recon.loop.model_parts`.

May import ``assess``, ``problem``, ``calibration`` and ``settings``.
"""
