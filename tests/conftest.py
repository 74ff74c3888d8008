"""Fixtures shared by several test modules."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def scene16():
    """A 32×32, 4-slice letters scene with 16 noisy images: 3 can be held out (tests of the TV choice and its pilot)."""
    from napari_fdt import Optics, simulate, source_grid
    from napari_fdt.sim.phantoms import text_phantom

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=4,
               slice_spacing_um=2.0, image_plane_um=0.0)
    return simulate(text_phantom((32, 32), 4, text="UC", delta_n=0.05), o, source_grid(4, 8.0, 15.0), seed=2, device="cpu")


# -- the napari plugin tests' scene and napari's notifications (tests/test_napari_plugin*.py) --


@pytest.fixture(scope="module")
def tiny_sim():
    """A 32×32, 4-slice letters scene with 9 sources (the napari plugin tests)."""
    from napari_fdt import Optics, simulate, source_grid
    from napari_fdt.sim.phantoms import text_phantom

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=4, slice_spacing_um=2.0)
    return simulate(text_phantom((32, 32), 4, text="UC", delta_n=0.05), o, source_grid(3, 8.0, 15.0), seed=1, device="cpu")


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
    """The plugin's runs checkpoint under the user's cache (napari_fdt.napari.resume); in the tests, under a temporary
    folder instead (inherited by the computation processes the widget starts)."""
    import os

    before = os.environ.get("NAPARI_FDT_CHECKPOINTS")
    os.environ["NAPARI_FDT_CHECKPOINTS"] = str(tmp_path_factory.mktemp("plugin_checkpoints"))
    yield
    if before is None:
        os.environ.pop("NAPARI_FDT_CHECKPOINTS", None)
    else:
        os.environ["NAPARI_FDT_CHECKPOINTS"] = before
