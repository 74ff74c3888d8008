"""``python -m napari_fdt`` runs the ``fdt`` command line."""

import sys

from napari_fdt.cli import main

sys.exit(main())
