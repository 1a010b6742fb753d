"""EMVA 1288 analysis of a descriptor data set: parse -> data -> results -> calibration.

Each stage is a separate, testable function, as in the EMVA 1288 reference implementation:

1. parse: :func:`hdrcap.pipeline.io.emva_descriptor.read_emva_descriptor` (descriptor -> steps and image paths);
2. data: :func:`emva_data` streams the images once and reduces them to numbers (temporal
   pair statistics per exposure time, spatial sums of the non-uniformity stacks);
3. results: :func:`emva_results` computes the EMVA 1288 (Release 3.x) quantities: system
   gain K by the photon-transfer regression over 0-70 % of saturation, temporal dark noise,
   dark current, saturation, PRNU and DSNU;
4. :func:`emva_calibration` turns them into a :class:`hdrcap.pipeline.params.Calibration`;
   :func:`calibrate_descriptor` runs the four stages on a descriptor file.

Temporal steps are those with exactly two images (one pair); steps with more images are the
spatial (non-uniformity) stacks. The photon count may vary through the exposure time, through
the irradiance at a constant exposure time, or both: every bright pair is matched with the dark
pairs at its exposure time (averaged when there are several). Images of 8 to 16 bits, PNG,
TIFF or PGM; descriptor paths with either separator. Like the standard, no outlier clipping
is applied here.

Where the data cannot support a number the result says so instead of giving one: a dark
variance below 0.24 DN^2 is quantisation-limited (EMVA 1288: sigma_y.dark is then set to
0.49 DN and sigma_d is an upper limit, 0.40/K); the dark current needs dark pairs at >= 6
exposure times, a dark noise above the quantisation limit and a slope that is not negative
(otherwise it is omitted, with the reason).
Units: DN, DN^2, seconds, electrons; K in DN per electron.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hdrcap.pipeline.calibration.dark import fit_dark_current
from hdrcap.pipeline.calibration.gain import PhotonTransferFit, photon_transfer_gain
from hdrcap.pipeline.calibration.readout import QUANTISATION_LIMIT, QUANTISATION_VARIANCE
from hdrcap.pipeline.calibration.stats import PairStats, pair_statistics
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.emva_descriptor import EmvaDataset, read_emva_descriptor
from hdrcap.pipeline.io.raw import read_image16
from hdrcap.pipeline.params import Calibration, SensorParams
from hdrcap.pipeline.times import ExposureMap

__all__ = [
    "EmvaData",
    "EmvaResults",
    "emva_data",
    "emva_results",
    "emva_calibration",
    "calibrate_descriptor",
    "QUANTISATION_VARIANCE",
    "QUANTISATION_LIMIT",
    "MIN_DARK_TIMES",
]

#: A PGM header token (magic, width, height, maxval), after whitespace and comments.
_PGM_TOKEN = re.compile(rb"(?:\s|#[^\n]*\n)*(\S+)")

#: Distinct exposure times of dark pairs needed for the dark current (as for the calibration).
MIN_DARK_TIMES = 6

_QUANTISATION_RULE = (
    "EMVA 1288: dark variance below 0.24 DN^2 is quantisation-limited; sigma_y.dark is set to "
    "0.49 DN and sigma_d < sqrt(0.24 - 1/12)/K = 0.40/K is an upper limit"
)


@dataclass
class EmvaData:
    """Reduced EMVA 1288 data (the "data" stage).

    Attributes
    ----------
    texp : numpy.ndarray
        Exposure time of every bright step, s (steps ordered by photon count when every step
        gives one, else by exposure time and mean; times repeat when the irradiance varies).
    photons : numpy.ndarray
        Mean photons per pixel of the bright step (NaN when missing).
    u_y, s2_y : numpy.ndarray
        Mean (DN) and pair temporal variance (DN^2) of the bright pair.
    u_ydark, s2_ydark : numpy.ndarray
        Same for the dark pairs at the same exposure time (averaged when several).
    s2_y_stderr, s2_ydark_stderr : numpy.ndarray
        Standard errors of the pair variances (fourth moment), DN^2.
    spatial : dict
        ``L``, ``L_dark``, ``texp``, ``mean`` / ``mean_dark`` (spatial means of the averaged
        stacks, DN), ``s2_measured`` / ``s2_measured_dark`` (spatial variance of the averaged
        image), ``sigma2_stack`` / ``sigma2_stack_dark`` (mean per-pixel temporal variance),
        and the maps ``mean_map``, ``mean_map_dark``, ``var_map``, ``var_map_dark``.
    dark_slope_map : numpy.ndarray or None
        Per-photosite slope of the dark value against exposure time, DN/s.
    bits, width, height : int
    n_images : int
    dark_texp, dark_u, dark_s2, dark_s2_stderr : numpy.ndarray
        The dark series: each distinct exposure time of a dark pair (s, ascending), its mean
        (DN), temporal variance (DN^2) and the variance's standard error.
    """

    texp: np.ndarray
    photons: np.ndarray
    u_y: np.ndarray
    s2_y: np.ndarray
    u_ydark: np.ndarray
    s2_ydark: np.ndarray
    s2_y_stderr: np.ndarray
    s2_ydark_stderr: np.ndarray
    spatial: dict = field(default_factory=dict)
    dark_slope_map: np.ndarray | None = None
    bits: int = 12
    width: int = 0
    height: int = 0
    n_images: int = 0
    dark_texp: np.ndarray = field(default_factory=lambda: np.zeros(0))
    dark_u: np.ndarray = field(default_factory=lambda: np.zeros(0))
    dark_s2: np.ndarray = field(default_factory=lambda: np.zeros(0))
    dark_s2_stderr: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _read(path, shape) -> np.ndarray:
    """One image of the data set (PNG, TIFF or PGM), checked against the descriptor's size, DN."""
    data = _read_pgm(Path(path)) if Path(path).suffix.lower() in (".pgm", ".pnm") else read_image16(path, 1.0).data
    if data.shape != shape:
        raise InputError(
            f"{path}: size {data.shape[1]}x{data.shape[0]} differs from the descriptor's {shape[1]}x{shape[0]}"
        )
    return data


def _read_pgm(path: Path) -> np.ndarray:
    """A binary PGM (P5) image with its values as stored, DN (uint8 or uint16).

    Pillow rescales a PGM whose maxval is below 65535 to the full 16-bit range; EMVA 1288
    analysis needs the values the camera gave. Header: ``P5``, width, height, maxval
    (whitespace separated, ``#`` comments allowed), one whitespace, then the raster (one byte
    per value up to maxval 255, else two, big-endian).
    """
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise InputError(f"{path}: cannot read image ({err.strerror})") from None
    fields: list[bytes] = []
    pos = 0
    while len(fields) < 4:
        m = _PGM_TOKEN.match(raw, pos)
        if m is None:
            raise InputError(f"{path}: not a binary PGM (P5) image")
        fields.append(m.group(1))
        pos = m.end()
    if fields[0] != b"P5":
        raise InputError(f"{path}: not a binary PGM (P5) image (magic {fields[0][:8]!r})")
    w, h, maxval = (int(f) for f in fields[1:])
    if not 0 < maxval < 65536:
        raise InputError(f"{path}: PGM maxval {maxval} outside 1..65535")
    dtype = np.dtype(">u2") if maxval > 255 else np.dtype("u1")
    body = raw[pos + 1 : pos + 1 + w * h * dtype.itemsize]
    if len(body) < w * h * dtype.itemsize:
        raise InputError(f"{path}: PGM raster is truncated ({len(body)} of {w * h * dtype.itemsize} bytes)")
    data = np.frombuffer(body, dtype).reshape(h, w)
    return data.astype(np.uint16) if maxval > 255 else data.copy()


def emva_data(dataset: EmvaDataset, progress: Callable[[int], Any] | None = None) -> EmvaData:
    """Stream every image of ``dataset`` once and reduce it (the "data" stage).

    Memory: a few float64 maps (per-pixel sums for the spatial stacks and the per-pixel dark
    regression), independent of the number of images.

    Parameters
    ----------
    dataset : EmvaDataset
        The parsed descriptor (steps with exposure times in s and image paths).
    progress : callable, optional
        Called with the number of images read after each step or image.

    Returns
    -------
    EmvaData
        Pair means (DN) and variances (DN^2) per bright step with the dark at its exposure
        time, the dark series, the non-uniformity sums and the per-pixel dark slope (DN/s).

    Raises
    ------
    InputError
        A step with fewer than two images, a bright step without a dark pair at its exposure
        time, fewer than three bright steps, or an image of the wrong size.
    """
    shape = (dataset.height, dataset.width)
    bright: list[tuple[float, float, PairStats]] = []
    darks: ExposureMap[list[PairStats]] = ExposureMap()
    spatial: dict[str, Any] = {}
    dark = _DarkSums(shape)
    n_img = 0
    for step in dataset.steps:
        if len(step.images) < 2:
            raise InputError(
                f"{dataset.path}: step {step.kind} {step.exposure_time * 1e9:g} ns has "
                f"{len(step.images)} image(s); every step needs at least two"
            )
        if len(step.images) == 2:
            ps = _pair(step, shape, dark)
            if step.kind == "b":
                bright.append((step.exposure_time, _photons(step), ps))
            else:
                darks.setdefault(step.exposure_time, []).append(ps)
            n_img += 2
            if progress:
                progress(2)
        else:
            key = "bright" if step.kind == "b" else "dark"
            if key in spatial:
                raise InputError(f"{dataset.path}: more than one {key} non-uniformity stack")
            spatial[key] = _stack(step, shape, progress)
            n_img += len(step.images)
    series = _dark_series(darks)
    steps = _bright_steps(dataset, bright, darks)
    t_b = np.array([t for t, _, _ in steps])
    return EmvaData(
        texp=t_b,
        photons=np.array([ph for _, ph, _ in steps]),
        u_y=np.array([p.mean for _, _, p in steps]),
        s2_y=np.array([p.variance for _, _, p in steps]),
        u_ydark=np.array([_dark_at(darks, t)[0] for t in t_b]),
        s2_ydark=np.array([_dark_at(darks, t)[1] for t in t_b]),
        s2_y_stderr=np.array([p.variance_stderr for _, _, p in steps]),
        s2_ydark_stderr=np.array([_dark_at(darks, t)[2] for t in t_b]),
        spatial=_spatial_summary(spatial),
        dark_slope_map=dark.slope_map(),
        bits=dataset.bits,
        width=dataset.width,
        height=dataset.height,
        n_images=n_img,
        **series,
    )


def _photons(step: Any) -> float:
    """Photons per pixel of a bright step, NaN when the descriptor gives none."""
    return float(step.photons) if step.photons is not None else float("nan")


def _pair(step: Any, shape: tuple[int, int], dark: _DarkSums) -> PairStats:
    """Pair statistics of a temporal step (no clipping, as the standard); dark pairs also feed
    the per-pixel dark regression."""
    a, b = (_read(p, shape) for p in step.images)
    ps = pair_statistics(a, b, clip=None, exposure_time=step.exposure_time)
    if step.kind == "d":
        dark.add(0.5 * (a.astype(np.float64) + b), step.exposure_time)
    return ps


def _dark_at(darks: ExposureMap, t: float) -> tuple[float, float, float]:
    """Mean (DN), variance (DN^2) and its standard error of the dark pairs at ``t`` s."""
    pairs = darks[t]
    n = len(pairs)
    se = float(np.sqrt(sum(p.variance_stderr**2 for p in pairs))) / n
    return float(np.mean([p.mean for p in pairs])), float(np.mean([p.variance for p in pairs])), se


def _dark_series(darks: ExposureMap) -> dict[str, np.ndarray]:
    """The dark pairs by distinct exposure time (ascending), as EmvaData's dark_* fields."""
    times = sorted(darks.keys())
    vals = [_dark_at(darks, t) for t in times]
    return {
        "dark_texp": np.array(times, float),
        "dark_u": np.array([v[0] for v in vals]),
        "dark_s2": np.array([v[1] for v in vals]),
        "dark_s2_stderr": np.array([v[2] for v in vals]),
    }


def _bright_steps(dataset: EmvaDataset, bright: list, darks: ExposureMap) -> list:
    """The bright steps in order of photon count (when every step gives it) else of exposure
    time and mean; each must have a dark pair at its exposure time; >= 3 of them."""
    missing = [t for t, _, _ in bright if t not in darks]
    if missing:
        raise InputError(
            f"{dataset.path}: bright step at {missing[0] * 1e9:g} ns has no dark pair at that exposure "
            "time (EMVA 1288 needs one at every exposure time)"
        )
    if len(bright) < 3:
        raise InputError(f"{dataset.path}: {len(bright)} bright pairs; the photon-transfer method needs >= 3")
    if all(np.isfinite(ph) for _, ph, _ in bright):
        return sorted(bright, key=lambda e: e[1])
    return sorted(bright, key=lambda e: (e[0], e[2].mean))


class _DarkSums:
    """Per-pixel straight-line regression sums of the dark pairs' mean against time."""

    def __init__(self, shape: tuple[int, int]) -> None:
        self.shape = shape
        self.sy: np.ndarray | None = None
        self.sty: np.ndarray | None = None
        self.sn = self.st = self.stt = 0.0

    def add(self, m: np.ndarray, t: float) -> None:
        if self.sy is None or self.sty is None:
            self.sy = np.zeros(self.shape)
            self.sty = np.zeros(self.shape)
        self.sy += m
        self.sty += t * m
        self.sn += 1
        self.st += t
        self.stt += t * t

    def slope_map(self) -> np.ndarray | None:
        """Slope per photosite, DN/s (float32), or None with fewer than 3 dark pairs."""
        if self.sy is None or self.sty is None or self.sn < 3:
            return None
        return ((self.sn * self.sty - self.st * self.sy) / (self.sn * self.stt - self.st * self.st)).astype(np.float32)


def _stack(step: Any, shape: tuple[int, int], progress: Callable[[int], Any] | None) -> dict[str, Any]:
    """Per-pixel mean (DN) and temporal variance (DN^2) of a non-uniformity stack."""
    s = np.zeros(shape)
    q = np.zeros(shape)
    ref = None
    for p in step.images:
        x = _read(p, shape).astype(np.float64)
        if ref is None:
            ref = x.copy()
        x -= ref
        s += x
        q += x * x
        if progress:
            progress(1)
    L = len(step.images)
    assert ref is not None  # the caller's stacks hold > 2 images
    mean_map = s / L + ref
    var_map = (q - s * s / L) / (L - 1)
    return {"L": L, "texp": step.exposure_time, "mean_map": mean_map, "var_map": var_map, "photons": step.photons}


def _spatial_summary(spatial: dict[str, Any]) -> dict[str, Any]:
    """Spatial means and variances of the bright and dark stacks (both needed), DN, DN^2."""
    sp: dict[str, Any] = {}
    if "bright" in spatial and "dark" in spatial:
        for key, suffix in (("bright", ""), ("dark", "_dark")):
            d = spatial[key]
            sp["L" + suffix] = d["L"]
            sp["texp" + suffix] = d["texp"]
            sp["mean" + suffix] = float(d["mean_map"].mean())
            sp["s2_measured" + suffix] = float(d["mean_map"].var())
            sp["sigma2_stack" + suffix] = float(d["var_map"].mean())
            sp["mean_map" + suffix] = d["mean_map"]
            sp["var_map" + suffix] = d["var_map"]
        sp["photons"] = spatial["bright"]["photons"]
    return sp


@dataclass
class EmvaResults:
    """EMVA 1288 results (the "results" stage); names follow the reference implementation.

    Attributes
    ----------
    K, K_stderr : float
        System gain, DN per electron, by the photon-transfer regression (slope through the
        origin of s2_y - s2_ydark against u_y - u_ydark over 0-70 % of saturation).
    ptc : PhotonTransferFit
    index_u_ysat : int
        Saturation step: the step of maximum temporal variance.
    u_y_sat : float
        Mean at saturation, DN (bias included).
    sigma_y_dark : float
        Temporal dark noise, DN (dark variance extrapolated to zero exposure time when the
        dark pairs cover >= 3 times); 0.49 DN, an upper limit, when quantisation-limited.
    sigma_d : float
        Temporal dark noise in electrons, sqrt(sigma_y_dark^2 - 1/12) / K (an upper limit
        when quantisation-limited).
    u_I_mean, u_I_mean_stderr : float
        Dark current from the mean dark value, electrons per second; NaN when the data do not
        support it (see ``notes["dark_current"]``).
    R, QE : float
        Responsivity (DN per photon) and quantum efficiency (%) when photons are known.
    u_e_sat : float
        Saturation capacity, electrons.
    s2_y, s2_y_dark : float
        Spatial variances of the averaged stacks, corrected for the temporal noise left,
        DN^2.
    PRNU1288, DSNU1288 : float
        PRNU in % and DSNU in electrons (Release 3 definitions).
    quantisation_limited : bool
        The dark variance is below 0.24 DN^2 (EMVA 1288's rule applies).
    notes : dict of str
        Why a quantity is a limit or is omitted (``sigma_y_dark``, ``dark_current``).
    """

    K: float
    K_stderr: float
    ptc: PhotonTransferFit
    index_u_ysat: int
    u_y_sat: float
    sigma_y_dark: float
    sigma_d: float
    u_I_mean: float
    u_I_mean_stderr: float
    R: float
    QE: float
    u_e_sat: float
    s2_y: float = float("nan")
    s2_y_dark: float = float("nan")
    PRNU1288: float = float("nan")
    DSNU1288: float = float("nan")
    quantisation_limited: bool = False
    notes: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """The scalar results and the fit range's first and last step, as plain JSON values.

        Returns
        -------
        dict
            Units as the attributes; a quantity the data do not support is None (JSON null),
            with the reason in ``notes``.
        """
        out = {
            k: getattr(self, k)
            for k in (
                "K",
                "K_stderr",
                "index_u_ysat",
                "u_y_sat",
                "sigma_y_dark",
                "sigma_d",
                "u_I_mean",
                "u_I_mean_stderr",
                "R",
                "QE",
                "u_e_sat",
                "s2_y",
                "s2_y_dark",
                "PRNU1288",
                "DSNU1288",
                "quantisation_limited",
            )
        }
        for k, v in out.items():
            if isinstance(v, float) and not np.isfinite(v):
                out[k] = None
        out["notes"] = dict(self.notes)
        out["index_sensitivity_max"] = int(np.flatnonzero(self.ptc.used).max())
        out["index_sensitivity_min"] = int(np.flatnonzero(self.ptc.used).min())
        return {k: (v.item() if isinstance(v, np.generic) else v) for k, v in out.items()}


def emva_results(data: EmvaData, fit_fraction: float = 0.7) -> EmvaResults:
    """Compute the EMVA 1288 results from reduced data (the "results" stage).

    Parameters
    ----------
    data : EmvaData
        Output of :func:`emva_data`.
    fit_fraction : float
        Upper end of the photon-transfer fit range, fraction of saturation (0.7 in EMVA 1288).

    Returns
    -------
    EmvaResults
        K (DN/e-), dark noise (DN, e-), dark current (e-/s), saturation, PRNU (%), DSNU (e-).
    """
    x = data.u_y - data.u_ydark
    y = data.s2_y - data.s2_ydark
    isat = int(np.argmax(data.s2_y))
    sat = float(x[isat])
    # include index 0 even if tiny: the fit range is 0 .. fit_fraction of saturation
    try:
        ptc = photon_transfer_gain(
            np.where(x > 0, x, 1e-12), y, sat, fit_fraction, np.hypot(data.s2_y_stderr, data.s2_ydark_stderr)
        )
    except ValueError as err:  # too few usable levels: a data set the standard's method cannot use
        raise InputError(f"EMVA 1288 data: the photon-transfer fit cannot be made ({err})") from None
    K = ptc.g
    s2_dark0, notes = _dark_variance_at_zero(data), {}
    limited = s2_dark0 < QUANTISATION_LIMIT
    if limited:
        s2_dark0 = QUANTISATION_LIMIT
        notes["sigma_y_dark"] = _QUANTISATION_RULE
    sigma_y_dark = float(np.sqrt(s2_dark0))
    sigma_d = float(np.sqrt(s2_dark0 - QUANTISATION_VARIANCE) / K)
    u_I, u_I_se, why = _dark_current(data, K, ptc.g_stderr, limited)
    if why:
        notes["dark_current"] = why
    used = ptc.used
    ph = data.photons
    if np.all(np.isfinite(ph[used])) and np.all(ph[used] > 0):
        R = float(np.sum(ph[used] * x[used]) / np.sum(ph[used] ** 2))
        QE = 100.0 * R / K
    else:
        R = QE = float("nan")
    u_e_sat = sat / K
    sp = data.spatial
    s2_y = s2_y_dark = prnu = dsnu = float("nan")
    if not np.isfinite(R):
        notes["R"] = "omitted: the descriptor gives no photon count for some bright step"
    if not sp:
        notes["PRNU1288"] = notes["DSNU1288"] = "omitted: no bright and dark non-uniformity stacks (> 2 images)"
    else:
        s2_y = sp["s2_measured"] - sp["sigma2_stack"] / sp["L"]
        s2_y_dark = sp["s2_measured_dark"] - sp["sigma2_stack_dark"] / sp["L_dark"]
        signal = sp["mean"] - sp["mean_dark"]
        prnu = 100.0 * float(np.sqrt(max(s2_y - s2_y_dark, 0.0))) / signal
        dsnu = float(np.sqrt(max(s2_y_dark, 0.0))) / K
    return EmvaResults(
        K=K,
        K_stderr=ptc.g_stderr,
        ptc=ptc,
        index_u_ysat=isat,
        u_y_sat=float(data.u_y[isat]),
        sigma_y_dark=sigma_y_dark,
        sigma_d=sigma_d,
        u_I_mean=float(u_I),
        u_I_mean_stderr=float(u_I_se),
        R=R,
        QE=QE,
        u_e_sat=float(u_e_sat),
        s2_y=float(s2_y),
        s2_y_dark=float(s2_y_dark),
        PRNU1288=float(prnu),
        DSNU1288=float(dsnu),
        quantisation_limited=bool(limited),
        notes=notes,
    )


def _dark_variance_at_zero(data: EmvaData) -> float:
    """The dark temporal variance at zero exposure time, DN^2: the straight-line fit of the dark
    series when it covers >= 3 times, else the dark pair at the shortest time."""
    if data.dark_texp.size >= 3:
        return float(np.polyfit(data.dark_texp, data.dark_s2, 1)[1])
    return float(data.dark_s2[0])


def _dark_current(data: EmvaData, K: float, K_stderr: float, quantisation_limited: bool) -> tuple[float, float, str]:
    """Dark current from the mean dark level (e-/s) and its standard error (the slope's and
    K's, DN/e-, combined), or NaN and the
    reason when the data do not support it: dark pairs at fewer than ``MIN_DARK_TIMES``
    exposure times, a quantisation-limited dark noise (the mean of an undithered quantiser is
    not linear in the signal), or a slope within 3 standard errors of zero (not detected; the
    limit is given) or below (the level falls: bias drift, not dark current)."""
    nan = float("nan")
    n = data.dark_texp.size
    if n < MIN_DARK_TIMES:
        return nan, nan, (f"omitted: dark pairs at {n} exposure time(s); the dark current needs >= {MIN_DARK_TIMES}")
    if quantisation_limited:
        return nan, nan, "omitted: the dark noise is quantisation-limited, so the mean dark level is not linear"
    fit = fit_dark_current(data.dark_texp, data.dark_u)
    D, se = fit.slope / K, fit.slope_stderr / K
    if D < -3 * se:
        return nan, nan, f"omitted: the dark level falls with the exposure time ({D:.3g} +- {se:.2g} e-/s)"
    if D <= 3 * se:
        return nan, nan, f"not detected: {D:.3g} +- {se:.2g} e-/s, below {max(D, 0.0) + 3 * se:.3g} e-/s (3 sigma)"
    return float(D), float(np.hypot(se, D * K_stderr / K)), ""


def emva_calibration(
    data: EmvaData, results: EmvaResults, saturation: str = "frame", provenance: Mapping[str, Any] | None = None
) -> Calibration:
    """The camera model of an EMVA 1288 data set as a :class:`Calibration`.

    g = K; mu_R and sigma2_R from the dark pair at the shortest exposure time (pair
    difference); v_sat by Sec. 6 (``saturation="frame"``: mean - 3 std of the brightest
    bright frame pair's frames, estimated from its mean and pair variance) or by the EMVA 1288
    criterion (``"emva"``: the mean at the maximum of the temporal variance); the PRNU map
    a_j (Eq. 14) from the non-uniformity stacks (bright minus dark, normalised to mean 1) with
    its standard error; the dark-current map from the per-pixel dark regression.

    Parameters
    ----------
    data : EmvaData
        Output of :func:`emva_data`.
    results : EmvaResults
        Output of :func:`emva_results`.
    saturation : {"frame", "emva"}
        The v_sat criterion.
    provenance : mapping, optional
        Recorded with the result.

    Returns
    -------
    Calibration
        g (DN/e-), mu_R (DN), sigma2_R (DN^2), v_sat (DN), D (e-/s), their standard errors,
        the PRNU, bias and dark-current maps.

    Raises
    ------
    ValueError
        Unknown ``saturation`` criterion.
    """
    if saturation not in ("frame", "emva"):
        raise ValueError("saturation must be 'frame' or 'emva'")
    K = results.K
    mu_R = float(data.dark_u[0])
    sigma2_R = float(data.dark_s2[0])
    if results.quantisation_limited:  # the standard's convention: 0.24 DN^2, an upper limit
        sigma2_R = max(sigma2_R, QUANTISATION_LIMIT)
    if not (np.isfinite(sigma2_R) and sigma2_R > 0):
        raise InputError(
            f"dark images of the shortest exposure have temporal variance {sigma2_R!r} DN^2: no read noise to measure"
        )
    white = float(2**data.bits - 1)
    if saturation == "emva":
        v_sat = results.u_y_sat
        v_method = "EMVA 1288: mean at maximum temporal variance"
    else:
        i = int(np.argmax(data.u_y))
        v_sat = float(data.u_y[i] - 3.0 * np.sqrt(max(data.s2_y[i], 0.0)))
        v_method = "Sec. 6: mean - 3 std of the brightest frames"
    sp = data.spatial
    prnu = prnu_se = bias_map = None
    prnu_std = float("nan")
    if sp:
        sig = sp["mean_map"] - sp["mean_map_dark"]
        norm = float(sig.mean())
        prnu = (sig / norm).astype(np.float32)
        prnu_se = (np.sqrt(sp["var_map"] / sp["L"] + sp["var_map_dark"] / sp["L_dark"]) / norm).astype(np.float32)
        prnu_std = results.PRNU1288 / 100.0
        bias_map = sp["mean_map_dark"].astype(np.float32)
    measured_D = bool(np.isfinite(results.u_I_mean))
    D = results.u_I_mean if measured_D else 0.0
    dmap = None if data.dark_slope_map is None or not measured_D else (data.dark_slope_map / K).astype(np.float32)
    params = SensorParams(
        g=K,
        mu_R=mu_R,
        sigma2_R=sigma2_R,
        v_sat=float(min(v_sat, white)),
        white_level=white,
        dark_current=float(D),
        name=str((provenance or {}).get("camera", "")),
    )
    prov = dict(provenance or {})
    prov["n_frames"] = int(data.n_images)
    prov["prnu_std"] = prnu_std
    n_spatial = int(sp.get("L", 0) + sp.get("L_dark", 0)) if sp else 0
    prov["frame_counts"] = {"temporal_pairs": int(2 * data.texp.size), "spatial": n_spatial}
    prov["calibration"] = {
        "gain_method": "EMVA 1288 photon-transfer regression (0-70 % of saturation)",
        "v_sat_method": v_method,
        "sigma2_R_method": "dark pair difference at the shortest exposure time"
        + (" (quantisation-limited: 0.24 DN^2, EMVA 1288)" if results.quantisation_limited else ""),
        "emva1288": results.to_dict(),
        "ptc": {
            "means": results.ptc.means.tolist(),
            "variances": results.ptc.variances.tolist(),
            "used": results.ptc.used.tolist(),
            "saturation": results.ptc.saturation,
            "g": results.K,
            "g_stderr": results.K_stderr,
        },
        "dark_series": {"times": data.dark_texp.tolist(), "levels": data.dark_u.tolist()},
        "notes": dict(results.notes),
    }
    if measured_D:
        prov["calibration"]["dark_fit"] = {"slope_DN_per_s": results.u_I_mean * K}
    else:
        prov["calibration"]["dark_current_note"] = f"{results.notes['dark_current']}; the model uses D = 0"
    n_pix = data.width * data.height
    stderr = {
        "g": results.K_stderr,
        "mu_R": float(np.sqrt(sigma2_R / (2 * n_pix))),
        "sigma2_R": float(sigma2_R * np.sqrt(2.0 / n_pix)),
    }
    if measured_D:
        stderr["dark_current"] = results.u_I_mean_stderr
    return Calibration(
        params=params,
        prnu=prnu,
        bias_map=bias_map,
        dark_current_map=dmap,
        stderr=stderr,
        provenance=prov,
        prnu_stderr=prnu_se,
    )


def calibrate_descriptor(
    descriptor: str | os.PathLike[str], saturation: str = "frame", provenance: Mapping[str, Any] | None = None
) -> tuple[Calibration, EmvaResults]:
    """All four stages on an EMVA 1288 descriptor file: parse, data, results, calibration.

    Parameters
    ----------
    descriptor : str or path-like
        The descriptor (``EMVA1288_Data.txt``); image paths are relative to its folder.
    saturation : {"frame", "emva"}
        The v_sat criterion, as in :func:`emva_calibration`.
    provenance : mapping, optional
        Recorded with the result (the camera defaults to "EMVA 1288 data set").

    Returns
    -------
    calibration : Calibration
        The camera model (g in DN/e-, mu_R in DN, sigma2_R in DN^2, v_sat in DN, D in e-/s).
    results : EmvaResults
        The EMVA 1288 quantities.
    """
    data = emva_data(read_emva_descriptor(descriptor))
    results = emva_results(data)
    prov = dict(provenance or {})
    prov.setdefault("camera", "EMVA 1288 data set")
    prov["source"] = f"EMVA 1288 descriptor {descriptor}"
    return emva_calibration(data, results, saturation=saturation, provenance=prov), results
