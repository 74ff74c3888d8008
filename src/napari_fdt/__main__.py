"""``python -m napari_fdt`` runs the ``fdt`` command line."""

import sys

from .cli import main

sys.exit(main())
