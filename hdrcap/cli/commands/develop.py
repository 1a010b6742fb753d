"""``hdrcap develop``: scene-linear RGB (demosaiced, colour matrix, sigma) from a merged CFA EXR."""

from __future__ import annotations

from pathlib import Path

import click

from hdrcap.cli.util import echo_json
from hdrcap.pipeline.develop_names import DEMOSAIC_METHODS, OUTPUT_SPACES
from hdrcap.pipeline.errors import InputError

__all__ = ["command"]

_METHODS = ", ".join(DEMOSAIC_METHODS)
_SPACES = ", ".join(OUTPUT_SPACES)


def _refuse_clobber(path: Path | None, force: bool, input_exr: Path) -> None:
    if path is None:
        return
    from hdrcap.pipeline.io.files import check_new_output

    check_new_output(path, force)
    if input_exr.exists() and path.exists() and input_exr.resolve() == path.resolve():
        raise InputError(f"{path}: is the input file; inputs are never modified, choose another output")


@click.command("develop")
@click.argument("input_exr", metavar="IN.exr", type=click.Path(path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True, help="Output RGB EXR.")
@click.option(
    "--demosaic",
    "method",
    default="malvar2004",
    show_default=True,
    help=f"Demosaicing method of colour-demosaicing ({_METHODS}); menon2007 is non-linear: no sigma.",
)
@click.option(
    "--space",
    default="camera",
    show_default=True,
    help=f"Output colour space ({_SPACES}); xyz and linear-srgb need the colour matrix the merge recorded.",
)
@click.option(
    "--preview", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Also write a tone-mapped PNG."
)
@click.option("--force", is_flag=True, help="Overwrite existing output files.")
@click.option("--json", "as_json", is_flag=True, help="Print a one-line JSON summary on stdout.")
def command(
    input_exr: Path, output: Path, method: str, space: str, preview: Path | None, force: bool, as_json: bool
) -> None:
    """Develop the CFA irradiance EXR of `hdrcap merge` into a scene-linear RGB EXR.

    Demosaics with colour-science's colour-demosaicing, applies the camera's colour matrix and
    white balance recorded by the merge (DNG tags or LibRaw), and propagates sigma per channel
    for the linear methods (bilinear, malvar2004). Channels R, G, B, sigma.R/G/B, nexp and
    quality (nexp = 0 or quality > 0: the pixel used a photosite saturated everywhere or
    defective). See docs/develop.md.
    """
    from hdrcap.pipeline.develop import develop_image
    from hdrcap.pipeline.io.exr import write_exr
    from hdrcap.pipeline.io.results import read_result

    _refuse_clobber(output, force, input_exr)
    _refuse_clobber(preview, force, input_exr)
    out = develop_image(read_result(input_exr), method, space, source=str(input_exr))
    precision: dict[str, str] = {name: "uint" for name in ("nexp", "quality") if name in out.channels}
    write_exr(output, out.channels, out.header, force=force, precision=precision)
    if preview is not None:
        import numpy as np

        from hdrcap.pipeline.preview import write_preview_png

        rgb = np.stack([out.channels[c] for c in "RGB"], axis=-1)
        write_preview_png(preview, rgb, None, force=force)
    info = {"output": str(output), "preview": None if preview is None else str(preview), **out.header["develop"]}
    info.pop("source_file")
    if as_json:
        echo_json(info)
    else:
        h, w = out.shape
        click.echo(
            f"wrote {output}: {w}x{h} RGB ({space}), demosaic {method}, "
            f"{'sigma per channel' if 'sigma.R' in out.channels else 'no sigma (non-linear method)'}, "
            f"{info['pixels_flagged']} pixels flagged"
        )
