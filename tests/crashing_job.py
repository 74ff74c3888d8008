"""A job for the plugin's computation process that dies as a native crash or an out-of-memory kill would (tests only).

``crash_after_first_stage`` runs :func:`napari_fdt.napari.jobs.job.reconstruction_job` and kills its own process with
SIGKILL once the first stage's end has been sent to napari's process.
"""

from __future__ import annotations

import os
import signal

from napari_fdt.napari.jobs.job import reconstruction_job
from napari_fdt.recon.loop.phases import TV_CHOICE


def crash_after_first_stage(**kwargs):
    for update in reconstruction_job(**kwargs):
        yield update
        if update.kind == "snapshot" and update.snapshot.stage_complete and update.snapshot.phase != TV_CHOICE:
            os.kill(os.getpid(), signal.SIGKILL)
