"""Reconstruction, in rooms that show the algorithm; each room imports only from the rooms below it (the contract
"recon's rooms" in ``pyproject.toml``, docs/architecture.md), and no module imports its package's ``__init__``.

From the top:

``run``          a whole run: the solver (:class:`~napari_fdt.recon.run.solver.Reconstructor`, the loop over stages
                 with the choices plugged in), a session (files in, files out), the report, half sets, the TV family.
``choices``      what a run chooses from its data and plugs into the stage loop: the TV weights' trials, the model
                 parts' pilot, tests, switches and backward step.
``loop``         one stage's loop and the run's state: the interface the choices see (:class:`~napari_fdt.recon.loop.interface.Run`),
                 the stage loop and its verdicts, the run state, snapshots, the validation error during a run,
                 checkpoints, the plan and its phases, and the records of the choices (TV weights, model parts).
``assess``       numbers about a volume or images: held-out splits and errors, metrics, Fourier shell correlation.
``problem``      what is optimised and how images are predicted: the RI volume, losses, stages and their images, the
                 batch order, which stages keep what fixed, the checks before a run, data-parallel groups.
``calibration``  the source positions, gains and optics fitted with the volume, and the sources' first fit from the images.
``settings``     the solver's settings, the step schedule, the ``fdt reconstruct`` line of a run.

Layer 3, beside :mod:`napari_fdt.sim` (neither imports the other).
"""
