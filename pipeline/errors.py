"""User-facing errors.

Every problem with the user's input (files, frames, options) is raised as an
:class:`HdrcapError` with a one-line message naming the file or value at fault. The command
line prints that line and exits non-zero; it never shows a traceback for these.
"""

__all__ = ["HdrcapError", "InputError", "OutputExistsError"]


class HdrcapError(Exception):
    """A problem the user can fix; ``str(err)`` is a complete one-line message."""

    exit_code = 2


class InputError(HdrcapError):
    """Bad input data: missing, unreadable, truncated, inconsistent or duplicate frames."""


class OutputExistsError(HdrcapError):
    """An output file already exists and ``force`` was not given."""

    exit_code = 3
