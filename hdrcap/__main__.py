"""``python -m hdrcap``: the command line."""

from hdrcap.cli import run

run()
