"""``hdrcap server start|stop|status``: the command server that starts commands warm."""

from __future__ import annotations

import click

from hdrcap.cli.util import echo_json


@click.group("server")
def command() -> None:
    """A command server: one process that has imported hdrcap and numba and set up the merge
    kernels, from which every later `hdrcap` command of the same user, Python and environment is
    forked, so that it starts warm (a small merge in a third of the time). Commands run as
    before when no server runs, or with HDRCAP_SERVER=0. See docs/merge.md, *The command
    server*."""


@command.command("start")
@click.option(
    "--idle-timeout",
    type=click.FloatRange(min=0),
    default=3600.0,
    show_default=True,
    help="End after this many seconds without a command (0: never).",
)
@click.option("--foreground", is_flag=True, help="Run the server in this process (Ctrl-C ends it).")
def start(idle_timeout: float, foreground: bool) -> None:
    """Start the command server of this Python and environment, detached (its log beside its
    socket), and wait until it listens. Says so when one runs already."""
    from hdrcap.cli import server

    running = server.status()
    if running is not None:
        click.echo(f"hdrcap server already running (pid {running['pid']}) at {running['socket']}")
        return
    if foreground:

        def ready(info: dict) -> None:
            click.echo(f"hdrcap server (pid {info['pid']}) listening at {info['socket']}", err=True)

        if server.serve(idle_timeout, on_ready=ready) != 0:
            click.echo("hdrcap server already running", err=True)
        return
    info = server.spawn(idle_timeout)
    click.echo(f"hdrcap server (pid {info['pid']}) listening at {info['socket']}")


@command.command("stop")
def stop() -> None:
    """Stop the command server of this Python and environment once its running commands end."""
    from hdrcap.cli import server

    info = server.stop()
    click.echo("no hdrcap server running" if info is None else f"hdrcap server (pid {info['pid']}) stopped")


@command.command("status")
@click.option("--json", "as_json", is_flag=True, help="Print one line of JSON.")
def status(as_json: bool) -> None:
    """Whether a command server of this Python and environment runs: its pid, key, start time
    and the commands it has served."""
    from hdrcap import _client
    from hdrcap.cli import server

    info = server.status()
    if as_json:
        echo_json({"running": info is not None, "key": _client.server_key()} | (info or {}))
        return
    if info is None:
        click.echo(f"no hdrcap server running (key {_client.server_key()})")
        return
    click.echo(
        f"hdrcap server running: pid {info['pid']}, key {info['key']}, started {info['started']}, "
        f"{info['requests']} command(s) served, {info['commands_running']} running, socket {info['socket']}"
    )
