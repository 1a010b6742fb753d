"""Make the before/after pictures of docs/develop.md: the demo scene in colour, merged and developed.

Not run by the tests. Run it from the repository root with the project's environment::

    .venv/bin/python docs/develop_pictures.py [WORK_FOLDER]

The demo scene (``hdr``: gradient, patches, edges; 4 decades) is tinted column by column with
eight linear sRGB colours and seen through a camera with a real colour matrix (Adobe's D65
matrix of the Canon EOS 5D Mark II, tests/helpers/colour_sim.py) under D65 light: each photosite
gets the irradiance its colour filter passes. The simulated camera-B shoots the demo's bracket, the frames carry that
matrix and the D65 white balance, ``hdrcap merge`` merges them without options beyond the
preset, and ``hdrcap develop --space linear-srgb`` develops the result. Written to docs/:
``develop_before.png`` (the merged CFA irradiance, one grey value per photosite, log
tone-mapped) and ``develop_after.png`` (the developed RGB, the same tone map).
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

DOCS = Path(__file__).resolve().parent
sys.path.insert(0, str(DOCS.parent))  # the tests' colour camera (tests/helpers/colour_sim.py)

from hdrcap.mock_camera.scenes import make_scene  # noqa: E402
from hdrcap.pipeline.io.exr import read_exr, write_exr  # noqa: E402
from hdrcap.pipeline.preview import write_preview_png  # noqa: E402
from tests.helpers.colour_sim import camera_mosaic, recolour_frames  # noqa: E402

#: The eight column tints (linear sRGB).
TINTS = np.array(
    [
        [1, 0.08, 0.05],
        [1, 0.45, 0.05],
        [0.9, 0.85, 0.1],
        [0.1, 0.8, 0.15],
        [0.1, 0.7, 0.9],
        [0.1, 0.2, 1],
        [0.8, 0.1, 0.9],
        [1, 1, 1],
    ]
)
SIZE = (256, 384)  # height, width: small PNGs for the docs


def _hdrcap(*args) -> None:
    subprocess.run([sys.executable, "-m", "hdrcap", *map(str, args)], check=True)


def colour_scene() -> np.ndarray:
    """The demo scene as per-photosite irradiance (e-/s) of the colour camera, RGGB mosaic."""
    h, w = SIZE
    grey = make_scene("hdr", SIZE, decades=4.0, x_max=2e5)
    tint = TINTS[np.minimum(np.arange(w) * len(TINTS) // w, len(TINTS) - 1)]
    return camera_mosaic(grey[..., None] * tint[None], 1.0)


def main(work: Path) -> None:
    work.mkdir(parents=True, exist_ok=True)
    write_exr(work / "scene.exr", {"irradiance": colour_scene().astype(np.float32)}, force=True)
    sim = work / "sim"
    _hdrcap("simulate", "--camera", "camera-B", "--scene", work / "scene.exr", "--out", sim, "--seed", "0", "--force")
    frames = recolour_frames(sorted(sim.glob("frame_*.dng")), work)
    _hdrcap("merge", *frames, "--camera", "camera-B", "-o", work / "m.exr", "--force")
    _hdrcap("develop", work / "m.exr", "-o", work / "rgb.exr", "--space", "linear-srgb", "--force")
    merged = read_exr(work / "m.exr").channels["irradiance"]
    write_preview_png(DOCS / "develop_before.png", merged, None, force=True)
    rgb = read_exr(work / "rgb.exr").channels["RGB"]
    write_preview_png(DOCS / "develop_after.png", rgb, None, force=True)
    for name in ("develop_before.png", "develop_after.png"):
        print(DOCS / name, (DOCS / name).stat().st_size // 1024, "KB")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="hdrcap-develop-")))
