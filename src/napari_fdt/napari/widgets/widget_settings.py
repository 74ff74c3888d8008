"""The reconstruction widget's settings as a file: the fields it shows over the last loaded settings, saved and loaded
in the format of ``fdt reconstruct --config`` (JSON, or TOML to read).

A mixin of :class:`~napari_fdt.napari.widgets.widget_reconstruction.ReconstructionWidget` (one concern per module); it uses
the widget's one widget per field of :data:`SETTING_FIELDS` (an attribute of the same name), ``_base`` (the settings
last loaded: those the widget does not show are kept for saving and running), ``feedback`` and ``native``.
"""

from __future__ import annotations

from pathlib import Path

from napari_fdt.napari.settings import format_stages, merge_config
from napari_fdt.recon.settings.config import SolverConfig, load_config

__all__ = ["SettingsFileActions", "SETTING_FIELDS"]

#: Settings the widget edits, by widget attribute (= SolverConfig field).
SETTING_FIELDS = ("stages", "coarse_model", "batch_size", "l1_l2_total", "ssim_weight", "tv_xy_weight", "tv_z_weight",
                  "calibrate_sources", "calibrate_gain", "calibrate_source_depth", "calibrate_pixel_size",
                  "calibrate_slice_spacing", "calibration_from_stage", "coherence", "mask_threshold", "seed", "snapshot_every",
                  "validation_fraction", "early_stopping", "pixel_integration", "obliquity_correction", "calibrate_pupil",
                  "calibrate_aberrations", "sub_slices", "half_set_resolution", "error_bounds")  # (no experimental setting: a loaded settings file keeps them)
#: Settings the widget numbers from 1 (as the status line does) while the configuration counts from 0.
_ONE_BASED = ("calibration_from_stage",)


class SettingsFileActions:
    """The settings in the widget, and their file."""

    def config(self) -> SolverConfig:
        """The settings in the widget over the last loaded ones, checked (raises :class:`FDTInputError`)."""
        values = {name: getattr(self, name).value for name in SETTING_FIELDS}
        for name in _ONE_BASED:
            values[name] = int(values[name]) - 1
        return merge_config(self._base, values)

    def set_config(self, config: SolverConfig) -> None:
        """Show ``config`` in the widget; settings it does not show are kept for saving and running."""
        self._base = config
        for name in SETTING_FIELDS:
            value = getattr(config, name)
            getattr(self, name).value = (format_stages(value) if name == "stages" else
                                         value + 1 if name in _ONE_BASED else value)

    def save_settings(self, path: str | Path) -> Path:
        """Write the settings as ``fdt reconstruct --config`` reads them."""
        self.config().save(path)
        return Path(path)

    def load_settings(self, path: str | Path) -> SolverConfig:
        """Read a settings file (JSON, or TOML for ``.toml``) into the widget."""
        config = load_config(path)
        self.set_config(config)
        return config

    def _save_settings_dialog(self) -> None:
        from qtpy.QtWidgets import QFileDialog

        path, _ = QFileDialog.getSaveFileName(self.native, "Save reconstruction settings", "fdt_settings.json", "JSON (*.json)")
        if path:
            with self.feedback.guard():
                self.feedback.info(f"settings written to {self.save_settings(path)}")

    def _load_settings_dialog(self) -> None:
        from qtpy.QtWidgets import QFileDialog

        path, _ = QFileDialog.getOpenFileName(self.native, "Load reconstruction settings", "", "Settings (*.json *.toml)")
        if path:
            with self.feedback.guard():
                self.load_settings(path)
                self.feedback.info(f"settings read from {path}")
