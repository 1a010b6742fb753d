"""The ``hdrcap`` command line: a thin layer over the Python API.

Commands live in :mod:`hdrcap.cli.commands` (one module each, discovered at start-up). Errors
the user can fix (:class:`pipeline.errors.HdrcapError`) are printed as one line
``hdrcap: error: ...`` with the error's exit status (:data:`acquire.capture.session.EXIT_CODES`), and
with ``--json`` also as a JSON object on stdout (:func:`acquire.capture.notify.error_summary`); a
local I/O error (disk full, permissions) exits 6; an unexpected exception is reported in
one line too (exit 70), with its traceback only when ``HDRCAP_DEBUG=1``.
"""

from __future__ import annotations

import importlib
import os
import pkgutil
import sys
from typing import NoReturn

import click

from hdrcap import __version__
from hdrcap.pipeline.errors import HdrcapError

__all__ = ["cli", "finish", "main", "run"]


class _Group(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(super().list_commands(ctx))


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="hdrcap")
@click.option("-v", "--verbose", count=True, help="More log messages on stderr (-v: run events, -vv: debug).")
@click.option("-q", "--quiet", count=True, help="Fewer log messages on stderr (errors only).")
def cli(verbose: int, quiet: int) -> None:
    """hdrcap: calibrated HDR capture with per-photosite uncertainty.

    Plans exposures for a target SNR, drives a camera (libgphoto2 or the built-in
    simulator), calibrates the sensor and merges raw brackets into the maximum-likelihood
    irradiance (electrons per second per photosite) and its standard deviation
    (Granados et al., "Optimal HDR Reconstruction with Linear Digital Cameras").
    Run `hdrcap COMMAND --help` for each command.
    """
    setup_logging(verbose - quiet)


#: The name of the stderr handler :func:`setup_logging` adds (once) to the ``hdrcap`` logger.
_HANDLER_NAME = "hdrcap.cli"


def setup_logging(level: int = 0) -> None:
    """Log messages of the ``hdrcap`` loggers (the run's events, warnings) to stderr through
    the standard :mod:`logging` module: ``level`` 0 warnings (faults, stops), 1 (-v) every
    event, 2 (-vv) debug, -1 (-q) errors only.

    Parameters
    ----------
    level : int
        Verbosity: -v counts up, -q counts down.
    """
    import logging

    logger = logging.getLogger("hdrcap")
    logger.setLevel({-1: logging.ERROR, 0: logging.WARNING, 1: logging.INFO}.get(max(-1, min(level, 2)), logging.DEBUG))
    if not any(h.get_name() == _HANDLER_NAME for h in logger.handlers):
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("hdrcap: %(levelname)s: %(message)s"))
        handler.set_name(_HANDLER_NAME)
        logger.addHandler(handler)
        logger.propagate = False


def _register() -> None:
    import hdrcap.cli.commands as pkg

    for mod in pkgutil.iter_modules(pkg.__path__):
        if mod.name.startswith("_"):
            continue
        module = importlib.import_module(f"hdrcap.cli.commands.{mod.name}")
        cmd = getattr(module, "command", None)
        if isinstance(cmd, click.Command):
            cli.add_command(cmd)


_register()


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``hdrcap`` console script; returns the exit status."""
    try:
        cli.main(args=argv, prog_name="hdrcap", standalone_mode=False)
        return 0
    except HdrcapError as err:
        args = sys.argv[1:] if argv is None else list(map(str, argv))
        if "--json" in args and not err.reported:  # the error as JSON too
            from hdrcap.acquire.capture.notify import error_summary
            from hdrcap.cli.util import echo_json

            echo_json(error_summary(err))
        click.echo(f"hdrcap: error: {err}", err=True)
        return err.exit_code
    except click.exceptions.Exit as err:
        return err.exit_code
    except click.ClickException as err:
        err.show()
        return err.exit_code
    except click.Abort:
        click.echo("hdrcap: aborted", err=True)
        return 130
    except KeyboardInterrupt:
        click.echo("hdrcap: interrupted", err=True)
        return 130
    except BrokenPipeError:
        return 1
    except OSError as err:  # our side: disk full, permissions, read-only file system
        click.echo(f"hdrcap: error: {err.filename or ''}{': ' if err.filename else ''}{err.strerror or err}", err=True)
        return 6
    except Exception as err:  # never a traceback for the user, unless asked for
        if os.environ.get("HDRCAP_DEBUG"):
            raise
        click.echo(
            f"hdrcap: internal error: {type(err).__name__}: {err} (set HDRCAP_DEBUG=1 for a traceback)",
            err=True,
        )
        return 70


def run() -> None:
    """The ``hdrcap`` command run in this process (the console script when no command server
    listens, :mod:`hdrcap._client`): :func:`main`, then :func:`finish` with its exit status."""
    finish(main())


def finish(status: int) -> NoReturn:
    """End the process with exit status ``status`` without tearing the interpreter down: what a
    command's process does after :func:`main`, in its own process or forked from the command
    server (:mod:`hdrcap.cli.server`).

    Every exit handler still runs (:mod:`atexit`: logging, temporary folders, zarr's loop) after
    the command's threads have finished, and stdout and stderr are flushed; only the teardown of
    the imported modules is skipped, which after numba's CPU target has been set up costs about
    0.25 s, a third of a small merge. A process that imported h5py (which closes its files as
    they are freed) is ended the usual way: ``SystemExit(status)`` is raised.
    """
    if "h5py" in sys.modules:
        sys.exit(status)
    import atexit
    import threading

    for thread in threading.enumerate():  # what sys.exit waits for, too
        if thread is not threading.main_thread() and not thread.daemon:
            thread.join()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe or stream: nothing more can be said
            status = status or 1
    os._exit(status)


if __name__ == "__main__":  # python -m hdrcap.cli
    run()
