"""The plugin's widgets (magicgui and Qt live here and nowhere else): the acquisition and reconstruction widgets, the
TV family's view, their sections, layers, curves, results and background tasks, and the settings' widgets generated
from the schema. A widget holds no physics. May import :mod:`napari_fdt.napari.jobs` and the plugin's other modules.
"""
