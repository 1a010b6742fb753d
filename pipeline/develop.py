"""Scene-linear RGB from a merged CFA irradiance mosaic: demosaic, colour matrix, propagated sigma.

The merge (Eq. 12) gives one irradiance per photosite of the Bayer mosaic. :func:`develop`
turns it into three colour channels per pixel:

1. Defective photosites (``quality`` bits dead, weak, hot, stuck) are replaced by the mean of
   their valid same-colour neighbours (the 8 photosites two steps away); photosites saturated
   in every exposure keep their value, a lower bound (Sec. 5).
2. The mosaic is demosaiced by colour-science's ``colour-demosaicing`` package
   (:data:`DEMOSAIC_METHODS`: bilinear, Malvar et al. 2004, Menon et al. 2007), never by code
   of ours.
3. A 3x3 matrix takes camera RGB to the output space (:func:`output_matrix`): ``camera`` (the
   demosaiced camera channels, no white balance), ``xyz`` (CIE XYZ, D50, the DNG connection
   space) or ``linear-srgb`` (ITU-R BT.709 primaries, D65 white, no transfer curve). The
   camera-to-XYZ matrix follows the DNG 1.4 specification (Chapter 6, "Mapping Camera Color
   Space to CIE XYZ Space") as implemented by colour-science's ``colour-hdri``: the white from
   AsShotNeutral (or AsShotWhiteXY), ColorMatrix1/2 interpolated at that white's correlated
   colour temperature, chromatic adaptation to D50 (Bradford). It is scaled so that a neutral
   surface whose camera values are ``k * n / max(n)`` (``n`` the AsShotNeutral) has Y = k in
   ``xyz`` and R = G = B = k in ``linear-srgb``: the unit stays the merge's (e-/s per
   photosite, or DN/s) of the neutral's strongest channel.

Uncertainty
-----------
Bilinear and Malvar demosaicing are linear filters, so each output value is
``y_pk = sum_q w_pqk x_q`` with weights that depend only on p - q and on p's place in the 2x2
tile; the colour matrix is folded into the weights. With independent photosites (the merge's
errors are independent from photosite to photosite, Eq. 12)::

    Var(y_pk) = sum_q w_pqk^2 sigma_q^2

The weights are measured from the library itself (its response to one unit impulse at each
of the four tile positions, :func:`linear_weights`), so the propagation follows whatever
filter the library applies. Within the filter's radius (1 bilinear, 2 Malvar) of the image
edge the library mirrors the image and a photosite can enter a pixel twice; there the sum is
taken by applying the library to sigma on sparse grids of photosites (:func:`_strip_variance`),
exact too. The three channels of a pixel share photosites: their errors are correlated, and
sigma gives each channel's standard deviation alone. Menon's method is non-linear (direction decisions): its sigma is not
propagated and no sigma channels are written (:data:`SIGMA_NOT_PROPAGATED`).

Flags
-----
Every output pixel gets ``nexp``, the smallest ``nexp`` of the photosites it was computed
from (its support: the photosites whose change changes it), and ``quality``, the bitwise OR of
their ``quality`` bits: 0 and ``nexp > 0`` mean every photosite used was a measurement.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hdrcap.pipeline.develop_names import DEMOSAIC_METHODS, LINEAR_METHODS, OUTPUT_SPACES
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.dngwrite import CameraColour
from hdrcap.pipeline.io.exr import ExrContent
from hdrcap.pipeline.result import HdrResult
from hdrcap.pipeline.schema import UNIT_ELECTRONS

__all__ = [
    "DEMOSAIC_METHODS",
    "LINEAR_METHODS",
    "OUTPUT_SPACES",
    "SIGMA_NOT_PROPAGATED",
    "CHANNELS_MEANING",
    "DevelopResult",
    "camera_to_xyz",
    "demosaic",
    "develop",
    "develop_image",
    "fill_defects",
    "linear_weights",
    "output_matrix",
    "propagate_variance",
    "support_radius",
    "white_xy",
]

#: Header statement for a non-linear method.
SIGMA_NOT_PROPAGATED = "sigma not propagated: the demosaicing method is non-linear; no sigma channels"

#: Photosites whose change can change an output pixel, per method, photosites from it
#: (measured by perturbing single photosites of random mosaics; tests/pipeline/test_develop.py checks it).
_SUPPORT_RADIUS = {"bilinear": 1, "malvar2004": 2, "menon2007": 8}
#: Bayer tiles colour_demosaicing knows.
_BAYER = ("RGGB", "BGGR", "GRBG", "GBRG")
#: Defect bits of the merge's quality channel (pipeline.params.DEFECT_BITS: dead, weak, hot, stuck).
_DEFECT_MASK = 1 | 2 | 4 | 8
#: Largest number of iterations of the AsShotNeutral -> white chromaticity search.
_WHITE_ITERATIONS = 100


def _check_method(method: str) -> None:
    if method not in DEMOSAIC_METHODS:
        raise InputError(f"unknown demosaicing method {method!r}; choose one of {', '.join(DEMOSAIC_METHODS)}")


def _check_cfa(cfa: object) -> str:
    cfa = str(cfa or "none").upper()
    if cfa in ("NONE", "MONO"):
        raise InputError(
            "develop makes colour from a Bayer mosaic, and this merge has no colour filter (a monochrome sensor, or "
            "PNG/TIFF frames merged without --cfa): its irradiance is the image already"
        )
    if cfa not in _BAYER:
        raise InputError(
            f"develop needs a 2x2 Bayer CFA mosaic ({', '.join(_BAYER)}); the header's CFA pattern is {cfa!r}"
        )
    return cfa


def support_radius(method: str) -> int:
    """Largest distance from which a photosite changes an output pixel.

    Parameters
    ----------
    method : str
        A key of :data:`DEMOSAIC_METHODS`.

    Returns
    -------
    int
        Photosites, per axis (measured by perturbing single photosites; Menon's is the largest).
    """
    _check_method(method)
    return _SUPPORT_RADIUS[method]


def demosaic(mosaic: np.ndarray, cfa: str, method: str = "malvar2004") -> np.ndarray:
    """Demosaic a Bayer mosaic with colour-science's ``colour-demosaicing``.

    Parameters
    ----------
    mosaic : numpy.ndarray
        (H, W) values of one unit (e.g. e-/s per photosite).
    cfa : str
        2x2 tile read row by row: ``RGGB``, ``BGGR``, ``GRBG`` or ``GBRG``.
    method : str
        A key of :data:`DEMOSAIC_METHODS`.

    Returns
    -------
    numpy.ndarray
        (H, W, 3) float64 camera RGB, the mosaic's unit.
    """
    _check_method(method)
    cfa = _check_cfa(cfa)
    import warnings

    with warnings.catch_warnings():  # colour-science's notes on optional packages, scipy's deprecations
        warnings.simplefilter("ignore")
        import colour_demosaicing

        fn = getattr(colour_demosaicing, DEMOSAIC_METHODS[method])
        return np.asarray(fn(np.asarray(mosaic, dtype=np.float64), cfa), dtype=np.float64)


def linear_weights(cfa: str, method: str, matrix: np.ndarray | None = None) -> np.ndarray:
    """The weights of a linear demosaic followed by ``matrix``, measured from the library.

    Parameters
    ----------
    cfa : str
        Bayer tile.
    method : str
        A linear method (:data:`LINEAR_METHODS`).
    matrix : numpy.ndarray, optional
        3x3 matrix applied to camera RGB (default identity).

    Returns
    -------
    numpy.ndarray
        (2, 2, 3, 2r+1, 2r+1), r the support radius: ``w[a, b, k, r + dy, r + dx]`` is the
        weight of a photosite at tile position (a, b) on channel k of the pixel (dy, dx) away.
    """
    if method not in LINEAR_METHODS:
        raise InputError(f"demosaicing method {method!r} is not linear: its sigma cannot be propagated")
    m = np.eye(3) if matrix is None else np.asarray(matrix, dtype=np.float64)
    r = support_radius(method)
    n = 4 * (r + 2)  # even: the tile phase of the impulse is that of the full image
    out = np.zeros((2, 2, 3, 2 * r + 1, 2 * r + 1))
    for a in (0, 1):
        for b in (0, 1):
            img = np.zeros((n, n))
            cy, cx = n // 2 + a, n // 2 + b
            img[cy, cx] = 1.0
            rgb = demosaic(img, cfa, method) @ m.T
            window = rgb[cy - r : cy + r + 1, cx - r : cx + r + 1]
            if not np.isclose(np.abs(rgb).sum(), np.abs(window).sum()):
                raise AssertionError(f"{method}: the library's support exceeds radius {r}")
            out[a, b] = np.moveaxis(window, 2, 0)
    return out


def propagate_variance(variance: np.ndarray, cfa: str, method: str, matrix: np.ndarray | None = None) -> np.ndarray:
    """Variance of a linear demosaic (and ``matrix``) of independent photosites.

    ``Var(y_pk) = sum_q w_pqk^2 Var(x_q)``: with the weights of :func:`linear_weights` (one
    convolution per tile position and channel) away from the image edge, and within the support
    radius of the edge by :func:`_edge_variance`, where the library's mirrored border makes the
    weights differ.

    Parameters
    ----------
    variance : numpy.ndarray
        (H, W) per-photosite variance, unit squared.
    cfa, method, matrix
        As for :func:`linear_weights`.

    Returns
    -------
    numpy.ndarray
        (H, W, 3) variance of each output channel.
    """
    from scipy.ndimage import convolve

    w2 = linear_weights(cfa, method, matrix) ** 2
    var = np.asarray(variance, dtype=np.float64)
    out = np.zeros((*var.shape, 3))
    for a in (0, 1):
        for b in (0, 1):
            phase = np.zeros_like(var)
            phase[a::2, b::2] = var[a::2, b::2]
            for k in range(3):
                out[..., k] += convolve(phase, w2[a, b, k], mode="constant")
    _edge_variance(out, var, cfa, method, matrix)
    return out


def _strip_variance(var: np.ndarray, cfa: str, method: str, m: np.ndarray) -> np.ndarray:
    """Exact variance of a linear demosaic of a small image, edges included.

    The library is applied to the standard deviations on a sparse grid of photosites, spaced so
    that no output pixel depends on two of them (4r + 2, r the support radius, mirrored copies
    included): each output then holds one photosite's weight times its sigma, and the squares
    summed over the grid's offsets give ``sum_q w_pq^2 sigma_q^2``.
    """
    step = 4 * support_radius(method) + 2
    sd = np.sqrt(var)
    out = np.zeros((*var.shape, 3))
    for oy in range(min(step, var.shape[0])):
        for ox in range(min(step, var.shape[1])):
            grid = np.zeros_like(sd)
            grid[oy::step, ox::step] = sd[oy::step, ox::step]
            out += (demosaic(grid, cfa, method) @ m.T) ** 2
    return out


def _edge_variance(out: np.ndarray, var: np.ndarray, cfa: str, method: str, matrix: np.ndarray | None) -> None:
    """Replace ``out`` within the support radius of each image edge by :func:`_strip_variance`
    of a strip along that edge (deep enough that its cut side does not reach the band; its
    start even, so the CFA tile is unchanged)."""
    m = np.eye(3) if matrix is None else np.asarray(matrix, dtype=np.float64)
    r = support_radius(method)
    depth = 4 * r + 2
    h, w = var.shape
    if h <= depth + 2 or w <= depth + 2:  # a small image: all of it
        out[...] = _strip_variance(var, cfa, method, m)
        return
    top = _strip_variance(var[:depth], cfa, method, m)
    out[:r] = top[:r]
    y0 = (h - depth) // 2 * 2
    bottom = _strip_variance(var[y0:], cfa, method, m)
    out[h - r :] = bottom[h - r - y0 :]
    left = _strip_variance(var[:, :depth], cfa, method, m)
    out[:, :r] = left[:, :r]
    x0 = (w - depth) // 2 * 2
    right = _strip_variance(var[:, x0:], cfa, method, m)
    out[:, w - r :] = right[:, w - r - x0 :]


def _same_colour_neighbour_sum(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Sum over the 8 same-colour neighbours (steps of 2) of ``values * weights``, zero outside."""
    p = np.pad(values * weights, 2)
    h, w = values.shape
    total = np.zeros((h, w))
    for dy in (-2, 0, 2):
        for dx in (-2, 0, 2):
            if dy or dx:
                total += p[2 + dy : 2 + dy + h, 2 + dx : 2 + dx + w]
    return total


def fill_defects(
    mosaic: np.ndarray, variance: np.ndarray, defect: np.ndarray, passes: int = 4
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Replace defective photosites by the mean of their valid same-colour neighbours.

    Parameters
    ----------
    mosaic : numpy.ndarray
        (H, W) irradiance.
    variance : numpy.ndarray
        (H, W) its variance.
    defect : numpy.ndarray
        (H, W) bool, True where the photosite is no measurement to keep.
    passes : int
        Rounds: a cluster of defects is filled from its edge inwards, one ring per round.

    Returns
    -------
    tuple of numpy.ndarray
        Filled mosaic, its variance (a mean of n independent values: sum of variances / n^2)
        and the mask of photosites still unfilled (no valid neighbour within ``passes`` rounds;
        they keep their value).
    """
    x = np.asarray(mosaic, dtype=np.float64).copy()
    v = np.asarray(variance, dtype=np.float64).copy()
    todo = np.asarray(defect, dtype=bool).copy()
    for _ in range(passes):
        if not todo.any():
            break
        valid = (~todo).astype(np.float64)
        n = _same_colour_neighbour_sum(np.ones_like(x), valid)
        can = todo & (n > 0)
        if not can.any():
            break
        mean = _same_colour_neighbour_sum(x, valid)[can] / n[can]
        var = _same_colour_neighbour_sum(v, valid)[can] / n[can] ** 2
        x[can], v[can] = mean, var
        todo &= ~can
    return x, v, todo


def white_xy(colour: CameraColour) -> np.ndarray:
    """CIE 1931 xy of the scene white: AsShotWhiteXY, or the chromaticity whose camera neutral
    (DNG 1.4, "Translating White Balance xy Coordinates to Camera Neutral Coordinates") is
    AsShotNeutral, found by the specification's fixed-point iteration.

    Parameters
    ----------
    colour : CameraColour
        The raw file's colour metadata.

    Returns
    -------
    numpy.ndarray
        (2,) CIE 1931 x, y of the white.

    Raises
    ------
    InputError
        No white balance in ``colour``, or an iteration that does not converge.
    """
    if colour.as_shot_white_xy is not None:
        return np.asarray(colour.as_shot_white_xy, dtype=np.float64)
    if colour.as_shot_neutral is None:
        raise InputError(
            "the raw file records no white balance (AsShotNeutral or camera multipliers); use --space camera"
        )
    from colour import XYZ_to_xy
    from colour_hdri.models.dng import matrix_XYZ_to_camera_space

    args = _dng_arguments(colour)
    neutral = np.asarray(colour.as_shot_neutral, dtype=np.float64)
    xy = np.array([1 / 3, 1 / 3])
    for _ in range(_WHITE_ITERATIONS):  # colour_hdri.camera_neutral_to_xy without a bound
        m = matrix_XYZ_to_camera_space(xy, *args[:7])
        new = np.asarray(XYZ_to_xy(np.linalg.solve(m, neutral)), dtype=np.float64)
        if np.max(np.abs(new - xy)) < 1e-9:
            return new
        xy = new
    raise InputError(f"the white chromaticity of AsShotNeutral {colour.as_shot_neutral} does not converge")


def _dng_arguments(colour: CameraColour) -> tuple:
    """colour_hdri's DNG arguments: CCT 1 and 2 (K), CM1, CM2, CC1, CC2, AB, FM1, FM2."""
    from colour_hdri.models.datasets.dng import CCT_ILLUMINANTS_ADOBEDNG, LIGHT_SOURCE_TAG_TO_DNG_ILLUMINANTS

    def cct(code: int | None) -> float:
        name = LIGHT_SOURCE_TAG_TO_DNG_ILLUMINANTS.get(code)
        if name not in CCT_ILLUMINANTS_ADOBEDNG:
            raise InputError(f"calibration illuminant {code} has no known colour temperature")
        return float(CCT_ILLUMINANTS_ADOBEDNG[name])

    def mat(v: Any) -> np.ndarray:
        return np.eye(3) if v is None else np.reshape(np.asarray(v, dtype=np.float64), (3, 3))

    two = colour.color_matrix_2 is not None and colour.illuminant_2 is not None
    cct1 = cct(colour.illuminant_1)
    cct2 = cct(colour.illuminant_2) if two else cct1
    cm2 = colour.color_matrix_2 if two else colour.color_matrix_1
    ab = np.ones(3) if colour.analog_balance is None else np.asarray(colour.analog_balance, dtype=np.float64)
    fm1, fm2 = colour.forward_matrix_1, colour.forward_matrix_2 if two else colour.forward_matrix_1
    cc1, cc2 = colour.camera_calibration_1, colour.camera_calibration_2 if two else colour.camera_calibration_1
    return (cct1, cct2, mat(colour.color_matrix_1), mat(cm2), mat(cc1), mat(cc2), ab, mat(fm1), mat(fm2))


def camera_to_xyz(colour: CameraColour) -> np.ndarray:
    """The camera-to-XYZ (D50) matrix of a raw file's colour metadata (DNG 1.4, Chapter 6).

    colour-hdri's ``matrix_camera_space_to_XYZ`` at the white of :func:`white_xy`, scaled so
    that the camera neutral ``n / max(n)`` maps to Y = 1.

    Parameters
    ----------
    colour : CameraColour

    Returns
    -------
    numpy.ndarray
        3x3, camera RGB (the mosaic's unit) to XYZ D50 (Y in the same unit).
    """
    from colour import xy_to_XYZ
    from colour_hdri.models.dng import matrix_camera_space_to_XYZ, matrix_XYZ_to_camera_space

    xy = white_xy(colour)
    args = _dng_arguments(colour)
    m = np.asarray(matrix_camera_space_to_XYZ(xy, *args), dtype=np.float64)
    neutral: np.ndarray
    if colour.as_shot_neutral is not None:
        neutral = np.asarray(colour.as_shot_neutral, dtype=np.float64)
    else:
        neutral = matrix_XYZ_to_camera_space(xy, *args[:7]) @ xy_to_XYZ(xy)
    y = (m @ (neutral / neutral.max()))[1]
    if not (np.isfinite(y) and y > 0):
        raise InputError("the colour matrix maps the white to a non-positive luminance (corrupt colour metadata)")
    return m / y


def _xyz_d50_to_linear_srgb() -> np.ndarray:
    """XYZ (D50) to linear sRGB (D65): Bradford adaptation, then sRGB's own matrix."""
    from colour import RGB_COLOURSPACES, xy_to_XYZ
    from colour.adaptation import matrix_chromatic_adaptation_VonKries
    from colour_hdri.models.datasets.dng import CCS_ILLUMINANT_ADOBEDNG

    srgb = RGB_COLOURSPACES["sRGB"]
    cat = matrix_chromatic_adaptation_VonKries(
        xy_to_XYZ(CCS_ILLUMINANT_ADOBEDNG), xy_to_XYZ(srgb.whitepoint), "Bradford"
    )
    return np.asarray(srgb.matrix_XYZ_to_RGB, dtype=np.float64) @ np.asarray(cat, dtype=np.float64)


def output_matrix(space: str, colour: CameraColour | None) -> np.ndarray:
    """The 3x3 matrix from camera RGB to ``space``.

    Parameters
    ----------
    space : str
        One of :data:`OUTPUT_SPACES`.
    colour : CameraColour or None
        The raw file's colour metadata (needed for ``xyz`` and ``linear-srgb``).

    Returns
    -------
    numpy.ndarray
        3x3 float64.

    Raises
    ------
    InputError
        Unknown space, or a colour space without the metadata it needs.
    """
    if space not in OUTPUT_SPACES:
        raise InputError(f"unknown colour space {space!r}; choose one of {', '.join(OUTPUT_SPACES)}")
    if space == "camera":
        return np.eye(3)
    if colour is None:
        raise InputError(
            f"--space {space} needs the camera's colour matrix, and the EXR header records none "
            "(merged from frames without colour metadata); use --space camera"
        )
    m = camera_to_xyz(colour)
    return m if space == "xyz" else _xyz_d50_to_linear_srgb() @ m


def _support_footprint(method: str) -> np.ndarray:
    r = support_radius(method)
    if method in LINEAR_METHODS:  # exactly the photosites with a non-zero weight, any tile, channel, cfa
        w = np.abs(linear_weights("RGGB", method)).sum(axis=(0, 1, 2))
        return w[::-1, ::-1] > 0
    return np.ones((2 * r + 1, 2 * r + 1), dtype=bool)


def _flags(nexp: np.ndarray, quality: np.ndarray | None, method: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Smallest nexp and OR of the quality bits over each pixel's support."""
    from scipy.ndimage import maximum_filter, minimum_filter

    foot = _support_footprint(method)
    n_out = minimum_filter(np.asarray(nexp, dtype=np.float32), footprint=foot, mode="nearest")
    if quality is None:
        return n_out, None
    q = np.asarray(quality).astype(np.uint32)
    q_out = np.zeros(q.shape, dtype=np.uint32)
    for bit in (1 << i for i in range(int(q.max(initial=0)).bit_length())):
        q_out |= np.where(maximum_filter((q & bit) > 0, footprint=foot, mode="nearest"), bit, 0).astype(np.uint32)
    return n_out, q_out.astype(np.float32)


@dataclass(frozen=True)
class DevelopResult:
    """A developed image.

    Attributes
    ----------
    rgb : numpy.ndarray
        (H, W, 3) float32, the output space (unit of the merge for the neutral, see the module).
    sigma : numpy.ndarray or None
        (H, W, 3) float32 standard deviation per channel; None for a non-linear method.
    nexp : numpy.ndarray
        (H, W) float32, smallest nexp over each pixel's support.
    quality : numpy.ndarray or None
        (H, W) float32 bit field, OR over the support (None when the input has none).
    matrix : numpy.ndarray
        3x3 camera RGB to output.
    info : dict
        Method, space, counts of filled and flagged photosites, the sigma statement.
    """

    rgb: np.ndarray
    sigma: np.ndarray | None
    nexp: np.ndarray
    quality: np.ndarray | None
    matrix: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)


def develop(
    irradiance: np.ndarray,
    sigma: np.ndarray | None,
    nexp: np.ndarray | None,
    cfa: str,
    *,
    method: str = "malvar2004",
    space: str = "camera",
    colour: CameraColour | None = None,
    quality: np.ndarray | None = None,
) -> DevelopResult:
    """Demosaic a merged irradiance mosaic into scene-linear RGB with propagated sigma.

    Parameters
    ----------
    irradiance : numpy.ndarray
        (H, W) merged irradiance (Eq. 12), e-/s per photosite (or DN/s).
    sigma : numpy.ndarray or None
        (H, W) its standard deviation, same unit (None: no sigma output).
    nexp : numpy.ndarray or None
        (H, W) unsaturated exposures per photosite (None: all treated as measured).
    cfa : str
        Bayer tile of the mosaic.
    method : str
        Demosaicing method (:data:`DEMOSAIC_METHODS`).
    space : str
        Output space (:data:`OUTPUT_SPACES`).
    colour : CameraColour, optional
        The raw file's colour metadata (for ``xyz`` and ``linear-srgb``).
    quality : numpy.ndarray, optional
        (H, W) merge quality bits; defect bits mark photosites to fill from neighbours.

    Returns
    -------
    DevelopResult
    """
    _check_method(method)
    cfa = _check_cfa(cfa)
    irr = np.asarray(irradiance, dtype=np.float64)
    if irr.ndim != 2 or min(irr.shape) < 2 * support_radius(method) + 2:
        raise InputError(f"develop needs a 2-D mosaic larger than the filter support, got shape {irr.shape}")
    if not np.all(np.isfinite(irr)):
        raise InputError("develop: the irradiance holds NaN or infinite values")
    m = output_matrix(space, colour)
    var = np.zeros_like(irr) if sigma is None else np.asarray(sigma, dtype=np.float64) ** 2
    n_in = np.ones(irr.shape, dtype=np.float32) if nexp is None else np.asarray(nexp, dtype=np.float32)
    defect = np.zeros(irr.shape, dtype=bool)
    if quality is not None:
        defect = (np.asarray(quality).astype(np.uint32) & _DEFECT_MASK) > 0
    filled, var, unfilled = fill_defects(irr, var, defect)
    rgb = demosaic(filled, cfa, method) @ m.T
    sig = None
    if sigma is not None and method in LINEAR_METHODS:
        sig = np.sqrt(np.maximum(propagate_variance(var, cfa, method, m), 0)).astype(np.float32)
    n_out, q_out = _flags(n_in, quality, method)
    info = {
        "method": method,
        "space": space,
        "defects_filled": int(defect.sum() - unfilled.sum()),
        "defects_unfilled": int(unfilled.sum()),
        "pixels_flagged": int(
            np.count_nonzero(n_out == 0) if q_out is None else np.count_nonzero((n_out == 0) | (q_out > 0))
        ),
        "sigma": "standard deviation per channel, propagated through the linear demosaic and the matrix "
        "(independent photosites; channels of one pixel are correlated)"
        if sig is not None
        else (SIGMA_NOT_PROPAGATED if sigma is not None else "no sigma in the input"),
    }
    return DevelopResult(rgb.astype(np.float32), sig, n_out, q_out, m, info)


#: What each channel of a developed EXR holds (the header's ``channels``).
CHANNELS_MEANING = (
    "R, G, B: the output space's channels (unit in 'unit'); sigma.R, sigma.G, sigma.B: standard deviation of "
    "each (absent for a non-linear demosaic); nexp: smallest nexp of the photosites each pixel was computed from "
    "(0: one of them was saturated everywhere or defective); quality: OR of their quality bits"
)


def develop_image(
    result: HdrResult, method: str = "malvar2004", space: str = "camera", *, source: str = ""
) -> ExrContent:
    """Develop a merge (a CFA irradiance mosaic) into a scene-linear RGB image.

    Parameters
    ----------
    result : HdrResult
        What ``hdrcap merge`` wrote: irradiance, sigma, nexp, quality, and the header's
        ``cfa_pattern`` and ``camera_colour``.
    method, space : str
        As for :func:`develop`.
    source : str
        The input file's name, recorded in the header.

    Returns
    -------
    ExrContent
        Channels ``R``, ``G``, ``B``, ``sigma.R``/``G``/``B`` (linear methods), ``nexp``,
        ``quality`` (when the input has it); the header keeps the input's under ``source_header``.

    Raises
    ------
    InputError
        No irradiance channel, a non-Bayer mosaic, an unknown method or space, or a colour space
        the header's colour metadata cannot give.
    """
    attrs = result.header
    irr = np.asarray(result.irradiance)
    if irr.ndim != 2:
        raise InputError(f"{source or 'the EXR'}: the irradiance is not a 2-D mosaic; not an EXR of `hdrcap merge`")
    _check_method(method)
    _check_cfa(attrs.get("cfa_pattern"))
    colour = CameraColour.from_attrs(attrs["camera_colour"]) if attrs.get("camera_colour") is not None else None
    res = develop(
        irr,
        result.sigma,
        result.nexp,
        attrs["cfa_pattern"],
        method=method,
        space=space,
        colour=colour,
        quality=result.quality,
    )
    out = {name: res.rgb[..., k] for k, name in enumerate("RGB")}
    if res.sigma is not None:
        out.update({f"sigma.{name}": res.sigma[..., k] for k, name in enumerate("RGB")})
    out["nexp"] = res.nexp
    if res.quality is not None:
        out["quality"] = res.quality
    from hdrcap import __version__

    head = {
        "unit": attrs.get("unit") or UNIT_ELECTRONS,
        "cfa_pattern": "none",
        "layout": "rgb",
        "channels": CHANNELS_MEANING,
        "sigma": res.info["sigma"],
        "colour_space": {
            "camera": "camera RGB as demosaiced, no white balance",
            "xyz": "CIE XYZ, D50 (DNG connection space); a neutral of camera values k n/max(n) has Y = k",
            "linear-srgb": "linear sRGB (BT.709 primaries, D65), no transfer curve; a neutral has R = G = B",
        }[space],
        "develop": {
            **res.info,
            "matrix_camera_to_output": res.matrix.tolist(),
            "camera_colour": None if colour is None else colour.to_attrs(),
            "source_file": source,
            "hdrcap_version": __version__,
        },
        "source_header": attrs,
    }
    return ExrContent(out, head)
