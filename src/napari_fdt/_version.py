"""The package version (one place: read by pyproject via setuptools, the CLI and reports)."""

__version__ = "0.1.0"
