"""User-facing errors.

Every problem with the user's input (files, frames, options) is raised as an
:class:`HdrcapError` with a one-line message naming the file or value at fault. The command
line prints that line and exits non-zero; it never shows a traceback for these.
"""

__all__ = ["HdrcapError", "InputError", "OutputExistsError"]


class HdrcapError(Exception):
    """A problem the user can fix; ``str(err)`` is a complete one-line message.

    The code that catches an error on its way up may add where it happened, for the reports
    (the JSON error object, notifications): ``run_dir`` the run folder of the capture it
    stopped, ``repetition`` the repetition of a scheduled job, ``reported`` true once it was
    printed as JSON (the command line then prints no second object).
    """

    exit_code = 2
    run_dir: str | None = None
    repetition: int | None = None
    reported: bool = False


class InputError(HdrcapError):
    """Bad input data: missing, unreadable, truncated, inconsistent or duplicate frames."""


class OutputExistsError(HdrcapError):
    """An output file already exists and ``force`` was not given."""

    exit_code = 3
