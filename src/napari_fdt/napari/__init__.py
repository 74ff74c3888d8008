"""The napari plugin (npe2 manifest ``napari.yaml``): reader, writer, sample data, widgets and their background jobs.

Top layer, beside :mod:`napari_fdt.cli`. A widget holds no physics: it calls the same core as the CLI. Importing
this package imports neither napari nor Qt; the widget modules do. See docs/architecture.md.
"""
