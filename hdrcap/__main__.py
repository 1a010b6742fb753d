"""``python -m hdrcap``: the command line (through the command server when one runs)."""

from hdrcap._client import run

run()
