"""Errors a user can cause, each naming the offending field and the fix.

Every check in the package raises :class:`FDTInputError` (a ``ValueError``) before any long
computation starts, so the command line can print one clear line and exit non-zero, and the
napari widgets can show the same message.
"""

from __future__ import annotations

__all__ = ["FDTInputError", "FDTWarning"]


class FDTInputError(ValueError):
    """Invalid user input: a file, a metadata field, an optical parameter or an array.

    Parameters
    ----------
    field:
        Name of the offending field as the user wrote it (e.g. ``"na"``, ``"images"``,
        ``"sources_um[3]"``).
    problem:
        What is wrong, with the offending value.
    fix:
        What the user should do about it.
    """

    def __init__(self, field: str, problem: str, fix: str = "") -> None:
        self.field = field
        self.problem = problem
        self.fix = fix
        message = f"{field}: {problem}"
        if fix:
            message += f" ({fix})"
        super().__init__(message)

    def __reduce__(self):  # pickled with its three parts (the plugin's computation process sends errors to napari's)
        return type(self), (self.field, self.problem, self.fix)


class FDTWarning(UserWarning):
    """A geometry or sampling the model can run but not represent faithfully."""
