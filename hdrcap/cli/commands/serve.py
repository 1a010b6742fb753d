"""``hdrcap serve ROOT``: a read-only web page and JSON API over run folders and archives."""

from __future__ import annotations

from pathlib import Path

import click


@click.command("serve")
@click.argument("root", type=click.Path(file_okay=False, path_type=Path))
@click.option(
    "--archive",
    "archives",
    multiple=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="A zarr archive of `hdrcap batch` to show (repeat for several).",
)
@click.option(
    "--host", default="127.0.0.1", show_default=True, help="Address to listen on; any but loopback needs a token."
)
@click.option(
    "--port", type=click.IntRange(0, 65535), default=8765, show_default=True, help="TCP port (0: any free one)."
)
@click.option(
    "--token",
    envvar="HDRCAP_SERVE_TOKEN",
    default=None,
    help="Require this token (16+ characters) on every request; also from HDRCAP_SERVE_TOKEN.",
)
def command(root: Path, archives: tuple[Path, ...], host: str, port: int, token: str | None) -> None:
    """Serve a read-only web page over the run folders in ROOT (its subfolders, as `hdrcap run`
    writes them) and the archives: runs and their state, live; each run's preview, SNR, sigma
    and quality maps, plan, events and files; a region's irradiance over an archive's runs.
    Nothing is written or run. See docs/serve.md (safety, ssh port forwarding, systemd)."""
    from hdrcap.serve import serve

    serve(root, archives, host=host, port=port, token=token, echo=lambda s: click.echo(s, err=True))
