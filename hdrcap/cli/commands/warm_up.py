"""``hdrcap warm-up``: compile the merge kernels ahead of the first merge."""

from __future__ import annotations

import time

import click

from hdrcap.cli.util import echo_json


@click.command("warm-up")
@click.option("--json", "as_json", is_flag=True, help="Print JSON on stdout.")
def command(as_json: bool) -> None:
    """Compile the merge kernels for this CPU into numba's cache (once after an install or an
    upgrade: 20-60 s), so that the first `hdrcap merge` only loads them. Later runs find them
    compiled and take about a second. `make demo` runs it first."""
    from hdrcap.pipeline.merge.accumulator import compile_kernels

    t0 = time.perf_counter()
    ready = compile_kernels()
    seconds = time.perf_counter() - t0
    if as_json:
        echo_json({"kernels": ready, "seconds": round(seconds, 2)})
        return
    click.echo(f"merge kernels ready ({'; '.join(ready)}): {seconds:.1f} s")
