"""EMVA 1288 analysis of a descriptor data set: parse -> data -> results -> calibration.

Each stage is a separate, testable function, as in the EMVA 1288 reference implementation:

1. parse: :func:`hdrcap.pipeline.io.read_emva_descriptor` (descriptor -> steps and image paths);
2. data: :func:`emva_data` streams the images once and reduces them to numbers (temporal
   pair statistics per exposure time, spatial sums of the non-uniformity stacks);
3. results: :func:`emva_results` computes the EMVA 1288 (Release 3.x) quantities: system
   gain K by the photon-transfer regression over 0-70 % of saturation, temporal dark noise,
   dark current, saturation, PRNU and DSNU;
4. :func:`emva_calibration` turns them into a :class:`hdrcap.pipeline.params.Calibration`;
   :func:`calibrate_descriptor` runs the four stages on a descriptor file.

Temporal steps are those with exactly two images (one pair); steps with more images are the
spatial (non-uniformity) stacks. Like the standard, no outlier clipping is applied here.
Units: DN, DN^2, seconds, electrons; K in DN per electron.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .calibration.dark import fit_dark_current
from .calibration.gain import PhotonTransferFit, photon_transfer_gain
from .calibration.stats import pair_statistics
from .errors import InputError
from .io import EmvaDataset, read_emva_descriptor, read_image16
from .params import Calibration, SensorParams
from .times import ExposureMap, unique_exposures

__all__ = ["EmvaData", "EmvaResults", "emva_data", "emva_results", "emva_calibration", "calibrate_descriptor",
           "QUANTISATION_VARIANCE"]

#: Variance of a uniform quantiser with a 1 DN step, DN^2.
QUANTISATION_VARIANCE = 1.0 / 12.0


@dataclass
class EmvaData:
    """Reduced EMVA 1288 data (the "data" stage).

    Attributes
    ----------
    texp : numpy.ndarray
        Exposure time of every temporal step, s (sorted).
    photons : numpy.ndarray
        Mean photons per pixel of the bright step (NaN when missing).
    u_y, s2_y : numpy.ndarray
        Mean (DN) and pair temporal variance (DN^2) of the bright pair.
    u_ydark, s2_ydark : numpy.ndarray
        Same for the dark pair at the same exposure time.
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


def _read(path, shape) -> np.ndarray:
    fr = read_image16(path, 1.0)
    if fr.data.shape != shape:
        raise InputError(f"{path}: size {fr.data.shape[1]}x{fr.data.shape[0]} differs from the descriptor's "
                         f"{shape[1]}x{shape[0]}")
    return fr.data


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
        Pair means (DN) and variances (DN^2) per exposure time, the non-uniformity sums and
        the per-pixel dark slope (DN/s).

    Raises
    ------
    InputError
        A step with fewer than two images, duplicate steps, an exposure time without its
        dark or bright pair, fewer than three temporal steps, or an image of the wrong size.
    """
    shape = (dataset.height, dataset.width)
    temporal: ExposureMap[dict[str, Any]] = ExposureMap()
    spatial: dict[str, Any] = {}
    dark = _DarkSums(shape)
    n_img = 0
    for step in dataset.steps:
        if len(step.images) < 2:
            raise InputError(f"{dataset.path}: step {step.kind} {step.exposure_time * 1e9:g} ns has "
                             f"{len(step.images)} image(s); every step needs at least two")
        if len(step.images) == 2:
            _add_pair(dataset, step, shape, temporal, dark)
            n_img += 2
            if progress:
                progress(2)
        else:
            key = "bright" if step.kind == "b" else "dark"
            if key in spatial:
                raise InputError(f"{dataset.path}: more than one {key} non-uniformity stack")
            spatial[key] = _stack(step, shape, progress)
            n_img += len(step.images)
    times = _temporal_times(dataset, temporal)

    def arr(kind, attr):
        return np.array([getattr(temporal[t][kind], attr) if attr != "mean" else temporal[t][kind].mean
                         for t in times])

    return EmvaData(
        texp=np.array(times), photons=np.array([temporal[t].get("photons", np.nan) for t in times], float),
        u_y=arr("b", "mean"), s2_y=arr("b", "variance"), u_ydark=arr("d", "mean"), s2_ydark=arr("d", "variance"),
        s2_y_stderr=arr("b", "variance_stderr"), s2_ydark_stderr=arr("d", "variance_stderr"),
        spatial=_spatial_summary(spatial), dark_slope_map=dark.slope_map(), bits=dataset.bits, width=dataset.width,
        height=dataset.height, n_images=n_img,
    )


class _DarkSums:
    """Per-pixel straight-line regression sums of the dark pairs' mean against time."""

    def __init__(self, shape: tuple[int, int]) -> None:
        self.shape = shape
        self.sy = self.sty = None
        self.sn = self.st = self.stt = 0.0

    def add(self, m: np.ndarray, t: float) -> None:
        if self.sy is None:
            self.sy = np.zeros(self.shape)
            self.sty = np.zeros(self.shape)
        self.sy += m
        self.sty += t * m
        self.sn += 1
        self.st += t
        self.stt += t * t

    def slope_map(self) -> np.ndarray | None:
        """Slope per photosite, DN/s (float32), or None with fewer than 3 dark pairs."""
        if self.sy is None or self.sn < 3:
            return None
        return ((self.sn * self.sty - self.st * self.sy) / (self.sn * self.stt - self.st * self.st)).astype(np.float32)


def _add_pair(dataset: EmvaDataset, step: Any, shape: tuple[int, int], temporal: ExposureMap,
              dark: _DarkSums) -> None:
    """Pair statistics of a temporal step (no clipping, as the standard); dark pairs also
    feed the per-pixel dark regression."""
    t = step.exposure_time
    a, b = (_read(p, shape) for p in step.images)
    ps = pair_statistics(a, b, clip=None, exposure_time=t)
    entry = temporal.setdefault(t, {})
    if step.kind in entry:
        raise InputError(f"{dataset.path}: two {step.kind} pairs at {t * 1e9:g} ns")
    entry[step.kind] = ps
    if step.kind == "b":
        entry["photons"] = step.photons if step.photons is not None else float("nan")
    else:
        dark.add(0.5 * (a.astype(np.float64) + b), t)


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
    mean_map = s / L + ref
    var_map = (q - s * s / L) / (L - 1)
    return {"L": L, "texp": step.exposure_time, "mean_map": mean_map, "var_map": var_map, "photons": step.photons}


def _temporal_times(dataset: EmvaDataset, temporal: ExposureMap) -> list[float]:
    """The exposure times with both a bright and a dark pair, s, ascending (>= 3 of them)."""
    times = sorted(t for t, e in temporal.items() if "b" in e and "d" in e)
    missing = [t for t, e in temporal.items() if not ("b" in e and "d" in e)]
    if missing:
        raise InputError(f"{dataset.path}: exposure time {missing[0] * 1e9:g} ns has no matching "
                         f"{'dark' if 'b' in temporal[missing[0]] else 'bright'} pair")
    if len(times) < 3:
        raise InputError(f"{dataset.path}: {len(times)} temporal steps; the photon-transfer method needs >= 3")
    return times


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
        Temporal dark noise, DN (dark variance extrapolated to zero exposure time).
    sigma_d : float
        Temporal dark noise in electrons, sqrt(sigma_y_dark^2 - 1/12) / K.
    u_I_mean, u_I_mean_stderr : float
        Dark current from the mean dark value, electrons per second.
    R, QE : float
        Responsivity (DN per photon) and quantum efficiency (%) when photons are known.
    u_e_sat : float
        Saturation capacity, electrons.
    s2_y, s2_y_dark : float
        Spatial variances of the averaged stacks, corrected for the temporal noise left,
        DN^2.
    PRNU1288, DSNU1288 : float
        PRNU in % and DSNU in electrons (Release 3 definitions).
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

    def to_dict(self) -> dict:
        """The scalar results and the fit range's first and last step, as plain JSON values.

        Returns
        -------
        dict
            Units as the attributes.
        """
        out = {k: getattr(self, k) for k in ("K", "K_stderr", "index_u_ysat", "u_y_sat", "sigma_y_dark", "sigma_d",
                                             "u_I_mean", "u_I_mean_stderr", "R", "QE", "u_e_sat", "s2_y",
                                             "s2_y_dark", "PRNU1288", "DSNU1288")}
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
    ptc = photon_transfer_gain(np.where(x > 0, x, 1e-12), y, sat, fit_fraction,
                               np.hypot(data.s2_y_stderr, data.s2_ydark_stderr))
    K = ptc.g
    # dark noise: extrapolate the dark variance to t = 0 when several times exist
    n_times = len(unique_exposures(data.texp))
    if n_times >= 3:
        slope, intercept = np.polyfit(data.texp, data.s2_ydark, 1)
        s2_dark0 = float(intercept)
    else:
        s2_dark0 = float(data.s2_ydark[0])
    sigma_y_dark = float(np.sqrt(max(s2_dark0, QUANTISATION_VARIANCE)))
    sigma_d = float(np.sqrt(max(s2_dark0 - QUANTISATION_VARIANCE, 0.0)) / K)
    if n_times >= 6:
        df = fit_dark_current(data.texp, data.u_ydark)
        u_I, u_I_se = df.slope / K, df.slope_stderr / K
    else:
        u_I, u_I_se = float("nan"), float("nan")
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
    if sp:
        s2_y = sp["s2_measured"] - sp["sigma2_stack"] / sp["L"]
        s2_y_dark = sp["s2_measured_dark"] - sp["sigma2_stack_dark"] / sp["L_dark"]
        signal = sp["mean"] - sp["mean_dark"]
        prnu = 100.0 * float(np.sqrt(max(s2_y - s2_y_dark, 0.0))) / signal
        dsnu = float(np.sqrt(max(s2_y_dark, 0.0))) / K
    return EmvaResults(K=K, K_stderr=ptc.g_stderr, ptc=ptc, index_u_ysat=isat,
                       u_y_sat=float(data.u_y[isat]), sigma_y_dark=sigma_y_dark, sigma_d=sigma_d,
                       u_I_mean=float(u_I), u_I_mean_stderr=float(u_I_se), R=R, QE=QE, u_e_sat=float(u_e_sat),
                       s2_y=float(s2_y), s2_y_dark=float(s2_y_dark), PRNU1288=float(prnu), DSNU1288=float(dsnu))


def emva_calibration(data: EmvaData, results: EmvaResults, saturation: str = "frame",
                     provenance: Mapping[str, Any] | None = None) -> Calibration:
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
    mu_R = float(data.u_ydark[0])
    sigma2_R = float(data.s2_ydark[0])
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
    D = max(results.u_I_mean, 0.0) if np.isfinite(results.u_I_mean) else 0.0
    dmap = None if data.dark_slope_map is None else (data.dark_slope_map / K).astype(np.float32)
    params = SensorParams(g=K, mu_R=mu_R, sigma2_R=sigma2_R, v_sat=float(min(v_sat, white)), white_level=white,
                          dark_current=float(D), name=str((provenance or {}).get("camera", "")))
    prov = dict(provenance or {})
    prov["n_frames"] = int(data.n_images)
    prov["prnu_std"] = prnu_std
    n_spatial = int(sp.get("L", 0) + sp.get("L_dark", 0)) if sp else 0
    prov["frame_counts"] = {"temporal_pairs": int(2 * data.texp.size), "spatial": n_spatial}
    prov["calibration"] = {
        "gain_method": "EMVA 1288 photon-transfer regression (0-70 % of saturation)",
        "v_sat_method": v_method,
        "sigma2_R_method": "dark pair difference at the shortest exposure time",
        "emva1288": results.to_dict(),
        "ptc": {"means": results.ptc.means.tolist(), "variances": results.ptc.variances.tolist(),
                "used": results.ptc.used.tolist(), "saturation": results.ptc.saturation,
                "g": results.K, "g_stderr": results.K_stderr},
        "dark_series": {"times": data.texp.tolist(), "levels": data.u_ydark.tolist()},
        "dark_fit": {"slope_DN_per_s": results.u_I_mean * K},
    }
    n_pix = data.width * data.height
    stderr = {
        "g": results.K_stderr,
        "mu_R": float(np.sqrt(sigma2_R / (2 * n_pix))),
        "sigma2_R": float(sigma2_R * np.sqrt(2.0 / n_pix)),
        "dark_current": results.u_I_mean_stderr,
    }
    return Calibration(params=params, prnu=prnu, bias_map=bias_map, dark_current_map=dmap, stderr=stderr,
                       provenance=prov, prnu_stderr=prnu_se)


def calibrate_descriptor(descriptor: str | os.PathLike[str], saturation: str = "frame",
                         provenance: Mapping[str, Any] | None = None) -> tuple[Calibration, EmvaResults]:
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
