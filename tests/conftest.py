"""Fixtures shared by several test modules."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def scene16():
    """The registry's tiny scene with 16 noisy images: 3 can be held out (tests of the TV choice and its pilot)."""
    from benchmarks.scenes import tiny_scene

    return tiny_scene(grid=4, seed=2)


# -- the napari plugin tests' scene and napari's notifications (tests/test_napari_plugin*.py) --


@pytest.fixture(scope="module")
def tiny_sim():
    """The registry's tiny scene (32×32 px, 4 slices, 9 sources; ``benchmarks.scenes.tiny_scene``): the plugin tests'."""
    from benchmarks.scenes import tiny_scene

    return tiny_scene(grid=3, seed=1)


@pytest.fixture()
def tiny_dir(tiny_sim, tmp_path):
    """``tiny_sim`` written as an acquisition folder."""
    from napari_fdt import write_acquisition

    return write_acquisition(tiny_sim.acquisition, tmp_path / "tiny")


@pytest.fixture()
def notifications():
    """Messages napari shows as notifications during the test."""
    seen: list[str] = []

    def keep(event):
        seen.append(str(getattr(event, "message", event)))

    from napari.utils.notifications import notification_manager

    notification_manager.notification_ready.connect(keep)
    yield seen
    notification_manager.notification_ready.disconnect(keep)


@pytest.fixture(autouse=True, scope="session")
def _plugin_checkpoints_in_a_temporary_folder(tmp_path_factory):
    """The plugin's runs checkpoint under the user's cache (napari_fdt.napari.jobs.resume); in the tests, under a temporary
    folder instead (inherited by the computation processes the widget starts)."""
    import os

    before = os.environ.get("NAPARI_FDT_CHECKPOINTS")
    os.environ["NAPARI_FDT_CHECKPOINTS"] = str(tmp_path_factory.mktemp("plugin_checkpoints"))
    yield
    if before is None:
        os.environ.pop("NAPARI_FDT_CHECKPOINTS", None)
    else:
        os.environ["NAPARI_FDT_CHECKPOINTS"] = before
