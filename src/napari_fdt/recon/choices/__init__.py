"""The choices a run makes from its data, plugged into the stage loop (:mod:`~napari_fdt.recon.choices.plugged`): the
TV weights' trials (:mod:`~napari_fdt.recon.choices.tv_search`) and the model parts' pilot before the first stage,
test at the last coarse stage's end, test at the finest stage's end, switches and backward step (``parts_*``).

A choice sees the run only through :class:`~napari_fdt.recon.loop.interface.Run`, never the solver class. May import
``loop`` and the rooms below it.
"""
