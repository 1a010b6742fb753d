"""A simulated bracket seen through a real camera's colour matrix, for the tests of ``hdrcap
develop`` and the pictures of docs/develop.md: published colorimetry, a colour scene as the
per-photosite irradiance of an RGGB mosaic, and simulated frames rewritten with DNG colour tags."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from hdrcap.mock_camera.dng import write_dng
from hdrcap.pipeline.io.raw import read_raw

#: XYZ (D65) to linear sRGB, IEC 61966-2-1 (published, 4 decimals).
XYZ_TO_SRGB = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])
SRGB_TO_XYZ = np.linalg.inv(XYZ_TO_SRGB)
#: Adobe's D65 ColorMatrix2 of the Canon EOS 5D Mark II (XYZ to camera), as LibRaw tabulates it.
CANON_CM = np.array([[0.4716, 0.0603, -0.0830], [-0.7798, 1.5474, 0.2480], [-0.1496, 0.1937, 0.6651]])
#: That camera's neutral under D65 light: its camera values of the D65 white.
CANON_NEUTRAL = CANON_CM @ (SRGB_TO_XYZ @ np.ones(3))
#: Tile positions of each colour of an RGGB mosaic.
RGGB = {(0, 0): 0, (0, 1): 1, (1, 0): 1, (1, 1): 2}


def mosaic(rgb_image: np.ndarray) -> np.ndarray:
    """An RGGB mosaic sampling an (H, W, 3) image."""
    h, w, _ = rgb_image.shape
    out = np.empty((h, w))
    for (a, b), c in RGGB.items():
        out[a::2, b::2] = rgb_image[a::2, b::2, c]
    return out


def camera_mosaic(srgb: np.ndarray, scale: float) -> np.ndarray:
    """The irradiance (e-/s) each photosite of the Canon camera gets from a linear sRGB (D65)
    image: a neutral of value 1 gives ``scale`` in the camera's strongest channel."""
    camera = np.einsum("ij,hwj->hwi", CANON_CM @ SRGB_TO_XYZ, srgb) * scale / CANON_NEUTRAL.max()
    return mosaic(camera)


def recolour_frames(frames, out_dir: Path) -> list[Path]:
    """The DNG ``frames`` rewritten into ``out_dir`` with the Canon matrix and D65 neutral."""
    out = []
    for path in frames:
        fr = read_raw(path)
        make, _, model = (fr.camera or "hdrcap Simulated").partition(" ")
        buf = io.BytesIO()
        write_dng(
            buf,
            fr.data,
            make=make,
            model=model,
            exposure_time=fr.exposure_time,
            iso=int(fr.iso),
            black_level=fr.black_level,
            white_level=int(fr.white_level),
            cfa=fr.cfa_pattern,
            color_matrix=CANON_CM,
            as_shot_neutral=tuple(CANON_NEUTRAL / CANON_NEUTRAL.max()),
        )
        (Path(out_dir) / Path(path).name).write_bytes(buf.getvalue())
        out.append(Path(out_dir) / Path(path).name)
    return out
