"""Helpers shared by the command modules: multi-value options and JSON output."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

__all__ = ["ManyValuesCommand", "many_values", "echo_json"]


class ManyValuesCommand(click.Command):
    """A click command whose options listed in ``many_value_options`` take several values
    after one flag (``--darks a.dng b.dng``), as well as the flag repeated.

    Values run until the next token that starts with ``-`` (a negative number still counts
    as a value).
    """

    many_value_options: tuple[str, ...] = ()

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        opts = set(getattr(self, "many_value_options", ()))
        out: list[str] = []
        current: str | None = None
        for tok in args:
            if tok == "--":
                current = None
                out.append(tok)
                continue
            if tok.startswith("-") and not _is_number(tok):
                current = tok if tok in opts else None
                if current is None:
                    out.append(tok)
                continue
            if current is not None:
                out.extend([current, tok])
            else:
                out.append(tok)
        return super().parse_args(ctx, out)


def _is_number(tok: str) -> bool:
    try:
        float(tok)
        return True
    except ValueError:
        return False


def many_values(*names: str) -> Callable[[click.Command], click.Command]:
    """Decorator: make a command parse ``names`` as multi-value options."""

    def deco(cmd: click.Command) -> click.Command:
        bases = (ManyValuesCommand, type(cmd))
        cmd.__class__ = type("ManyValues" + type(cmd).__name__, bases, {"many_value_options": tuple(names)})
        return cmd

    return deco


def echo_json(obj: Any) -> None:
    """Print ``obj`` as one line of JSON on stdout."""
    click.echo(json.dumps(obj, sort_keys=True, default=_default))


def _default(obj: object) -> object:
    import numpy as np

    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(type(obj).__name__)
