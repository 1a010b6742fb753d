"""The whole Sec. 6 calibration from streamed frames, as a sequence of named steps.

Order: bias (mu_R, sigma2_R, offset map) -> darks (master darks, dark current) -> saturation
(v_sat) -> flats (PRNU map Eq. 14) -> gain (pairs Eq. 16-17, photon-transfer regression) ->
dark current in electrons per second -> :class:`~hdrcap.pipeline.params.Calibration`. Each
step records its standard errors, methods and plot data in a :class:`_Record` that becomes the
calibration's ``stderr`` and ``provenance["calibration"]``.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hdrcap.pipeline.calibration.dark import (
    DarkCurrentMap,
    DarkFit,
    DarkSeries,
    MasterDark,
    shrink_dark_current_map,
    stream_master_darks,
)
from hdrcap.pipeline.calibration.defects import (
    DEFECT_BITS,
    DefectThresholds,
    defect_counts,
    hot_defects,
    neutral_prnu,
    response_defects,
)
from hdrcap.pipeline.calibration.flats import FlatResult, estimate_flats
from hdrcap.pipeline.calibration.gain import (
    DarkVariance,
    PhotonTransferFit,
    fit_dark_variance,
    gain_from_pairs,
    linear_range_warnings,
    nonlinearity_warnings,
    photon_transfer_gain,
    prnu_correction_factor,
    usable_pairs,
)
from hdrcap.pipeline.calibration.readout import ReadoutEstimate, estimate_readout
from hdrcap.pipeline.calibration.saturation import estimate_saturation
from hdrcap.pipeline.calibration.shutter import shutter_summary
from hdrcap.pipeline.calibration.stats import DEFAULT_CLIP, PairTap
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.params import Calibration, SensorParams

__all__ = ["GAIN_METHODS", "calibrate", "calibration_summary", "format_summary", "with_file_metadata"]

#: Gain estimators :func:`calibrate` knows.
GAIN_METHODS = ("auto", "pairs", "ptc")

_PTC_METHOD = "EMVA 1288 photon-transfer regression (0-70 % of saturation)"


@dataclass
class _Record:
    """What the steps report: frame counts, standard errors of the scalars and the
    ``provenance["calibration"]`` entry (methods, series for the plots)."""

    counts: dict[str, int] = field(default_factory=lambda: {"bias": 0, "saturation": 0, "flat": 0, "dark": 0})
    stderr: dict[str, float] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)
    dark_variance: DarkVariance | None = None


def _readout_step(bias: Iterable, clip: float | None, white_level: float | None, rec: _Record) -> ReadoutEstimate:
    ro = estimate_readout(bias, clip, white_level)
    rec.counts["bias"] = ro.n_frames
    rec.stderr.update(mu_R=ro.mu_R_stderr, sigma2_R=ro.sigma2_R_stderr)
    rec.info.update(
        sigma2_R_method=ro.method,
        bias_exposure_time=ro.exposure_time,
        bias_dsnu_DN=ro.dsnu,
        clip_sigma=clip,
        sigma2_R_quantisation_limited=ro.quantisation_limited,
        sigma2_R_measured=ro.measured_sigma2,
        bias_drift_DN=ro.drift,
    )
    if ro.quantisation_limited:
        rec.info.setdefault("warnings", []).append(
            f"bias frames are quantisation-limited (pair variance {ro.measured_sigma2:.3g} DN^2 < 0.24 DN^2): "
            f"sigma2_R set to 0.24 DN^2, an upper limit (EMVA 1288; the truth lies in 1/12..0.24 DN^2), and "
            f"mu_R carries the quantiser's bias (standard error {ro.mu_R_stderr:.2g} DN)"
        )
    return ro


def _dark_step(
    darks: Iterable | None,
    ro: ReadoutEstimate,
    clip: float | None,
    dark_sink: Callable[[MasterDark], Any] | None,
    rec: _Record,
) -> tuple[DarkFit | None, DarkSeries | None]:
    """Master darks per exposure time (each handed to ``dark_sink``), then the dark-current
    fit and the series (for the per-photosite maps) when it has >= 6 exposure times."""
    if darks is None:
        return None, None
    shape = None if ro.bias_map is None else ro.bias_map.shape
    series = DarkSeries()
    tap = PairTap(darks, clip)
    for master in stream_master_darks(tap, clip, shape):
        series.add(master)
        rec.counts["dark"] += master.n_frames
        if dark_sink is not None:
            dark_sink(master)
    rec.dark_variance = fit_dark_variance(tap.pairs)
    if not series.times:
        return None, None
    rec.info["dark_series"] = series.to_dict()
    if series.n_times() >= 6:
        return series.fit(), series
    if dark_sink is None:
        raise InputError(
            f"dark current needs dark frames at >= 6 exposure times, got {len(series.times)} "
            "(or give a dark library to store master darks only)"
        )
    return None, None


def _saturation_step(
    saturation: Iterable | None, white_level: float | None, ro: ReadoutEstimate, clip: float | None, rec: _Record
) -> tuple[float, np.ndarray | None]:
    """v_sat (DN) from saturation frames (Sec. 6) or, without any, the white level."""
    sat_map = None
    if saturation is not None:
        v_sat, v_sat_se, sat_mean, sat_std, n_sat, sat_map = estimate_saturation(saturation, clip)
        rec.counts["saturation"] = n_sat
        rec.info["saturation_frame"] = {"mean": sat_mean, "std": sat_std}
        rec.stderr["v_sat"] = v_sat_se
        rec.info["v_sat_method"] = "saturation frame: mean - 3 std (Sec. 6)"
    else:
        if white_level is None:
            raise InputError("no saturation frame and no white level: cannot set v_sat")
        v_sat = float(white_level)
        rec.stderr["v_sat"] = 0.0
        rec.info["v_sat_method"] = "white level (no saturation frame given)"
    if v_sat <= ro.mu_R:
        raise InputError(
            f"saturation limit {v_sat:.1f} DN is not above the bias level {ro.mu_R:.1f} DN; "
            "is the saturation frame a dark or bias frame?"
        )
    return v_sat, sat_map


def _flat_step(
    flats: Iterable | None,
    ro: ReadoutEstimate,
    v_sat: float,
    clip: float | None,
    dark_slope_map: np.ndarray | None,
    rec: _Record,
) -> tuple[FlatResult, np.ndarray | None]:
    """The PRNU map (Eq. 14) and the flat pairs; the a_j error map includes the offset map's
    own noise (sigma2_R / n_bias, common to every flat)."""
    if flats is None:
        raise InputError("no flat fields given: the gain g and the PRNU map need flat fields")
    dark_ref = ro.bias_map if ro.bias_map is not None else ro.mu_R
    fl = estimate_flats(flats, dark_ref, v_sat, ro.sigma2_R, clip, dark_slope_map, mu_R=ro.mu_R)
    rec.counts["flat"] = fl.n_frames
    prnu_stderr = fl.prnu_stderr
    if prnu_stderr is not None and ro.bias_map is not None:
        prnu_stderr = np.square(prnu_stderr)
        prnu_stderr += np.float32(ro.sigma2_R / ro.n_frames / fl.mean_level**2)
        np.sqrt(prnu_stderr, out=prnu_stderr)
    if not fl.pairs:
        raise InputError("the gain needs at least two flat fields at the same exposure time (a pair, Eq. 16)")
    return fl, prnu_stderr


def _response_defect_step(
    fl: FlatResult,
    prnu_stderr: np.ndarray | None,
    ro: ReadoutEstimate,
) -> tuple[FlatResult, np.ndarray | None, np.ndarray]:
    """Dead, weak and stuck photosites (:mod:`.defects`); dead and stuck ones get a_j = 1 and
    the PRNU map and spread are taken over the normal photosites."""
    defects = response_defects(
        fl.prnu, prnu_stderr, fl.prnu_std, ro.bias_map, ro.mu_R, ro.sigma2_R, ro.n_frames, ro.dsnu
    )
    prnu, prnu_stderr, prnu_std = neutral_prnu(fl.prnu, prnu_stderr, defects)
    return dataclasses.replace(fl, prnu=prnu, prnu_std=prnu_std), prnu_stderr, defects


def _hot_defect_step(defects: np.ndarray, dmap: DarkCurrentMap | None, rec: _Record) -> np.ndarray:
    """Add the hot photosites (with a dark series) to the defect map; record the counts."""
    if dmap is not None:
        defects[hot_defects(dmap.raw, dmap.raw_stderr, dmap.prior_mean, dmap.prior_sd)] |= DEFECT_BITS["hot"]
    rec.info["defects"] = {
        "counts": defect_counts(defects),
        "hot_measured": dmap is not None,
        "thresholds": dataclasses.asdict(DefectThresholds()),
    }
    return defects


def _bias_stderr_map(ro: ReadoutEstimate) -> np.ndarray | None:
    """Standard error of the offset map, sqrt(sigma2_R / n_bias) DN, as a float32 map."""
    if ro.bias_map is None:
        return None
    return np.full(ro.bias_map.shape, np.sqrt(ro.sigma2_R / ro.n_frames), np.float32)


def _ptc_points(
    pairs: list, ro: ReadoutEstimate, dark_fit: DarkFit | None, dark_var: DarkVariance | None
) -> tuple[np.ndarray, np.ndarray, float, str]:
    """Photon-transfer points of the flat pairs (EMVA 1288): mean above dark (DN) and variance
    above the dark temporal variance (DN^2), both at each pair's exposure time.

    With a dark-current fit and dark pairs at >= 2 times, the dark mean and the dark temporal
    variance at the pair's time are subtracted; otherwise neither is (the dark signal then
    counts as signal in both coordinates, which leaves the slope unbiased). Also returns the
    standard error common to every point (of the subtracted variance, DN^2) and how the dark
    was handled.
    """
    x = np.array([p.mean - ro.mu_R for p in pairs])
    times = np.array([p.exposure_time for p in pairs])
    if dark_fit is None or dark_var is None:
        y = np.array([p.variance - ro.sigma2_R for p in pairs])
        why = "no dark fit" if dark_fit is None else "no dark pairs at >= 2 exposure times"
        return x, y, ro.sigma2_R_stderr, f"readout mean and variance subtracted; dark signal counted as signal ({why})"
    x = x - dark_fit.slope * times
    y = np.array([p.variance - dark_var.at(p.exposure_time)[0] for p in pairs])
    common = dark_var.at(float(np.mean(times)))[1]
    how = (
        f"dark mean (fit) and dark temporal variance ({dark_var.n_pairs} dark pairs, "
        f"{dark_var.slope:.4g} DN^2/s) subtracted at each pair's exposure time"
    )
    return x, y, common, how


def _gain_step(
    fl: FlatResult,
    ro: ReadoutEstimate,
    v_sat: float,
    dark_fit: DarkFit | None,
    gain_method: str,
    fit_fraction: float,
    rec: _Record,
) -> tuple[float, float]:
    """g and its standard error, DN per electron: the Eq. 16 average over every usable flat
    pair, whatever its level (with the Eq. 17 factor k from the flats' dark/light signal
    ratio), and the photon-transfer regression over the levels within ``fit_fraction`` of
    saturation (EMVA 1288). Records which pairs served and why, and warns when the
    photon-transfer points depart from the line near saturation."""
    t_flat = float(np.mean([p.exposure_time for p in fl.pairs]))
    dark_dn = dark_fit.slope * t_flat if dark_fit is not None else 0.0
    k = prnu_correction_factor(fl.mean_level, fl.prnu_std**2, max(dark_dn, 0.0))
    sat_span = v_sat - ro.mu_R
    g_pairs: float | None = None
    g_pairs_se: float | None = None
    per_pair: list[float] = []
    ok_pairs, pair_log = usable_pairs(fl.pairs, ro.mu_R, sat_span)
    if ok_pairs:
        g_pairs, g_pairs_se, per_pair = gain_from_pairs(ok_pairs, ro.mu_R, ro.sigma2_R, k, ro.sigma2_R_stderr)
    x, y, common_se, dark_how = _ptc_points(ok_pairs, ro, dark_fit, rec.dark_variance)
    n_levels = int(np.unique(np.round(x[(x > 0) & (x <= fit_fraction * sat_span)], 6)).size)
    ptc = None
    var_se = np.array([p.variance_stderr for p in ok_pairs])
    if n_levels >= 3:
        ptc = photon_transfer_gain(x, y, sat_span, fit_fraction, var_se, common_se)
    if gain_method == "ptc" and ptc is None:
        raise InputError(
            f"the photon-transfer regression needs flat pairs at >= 3 levels within "
            f"{fit_fraction:.0%} of saturation; got {n_levels}"
        )
    if g_pairs is None or g_pairs_se is None:  # gain_from_pairs gives both
        raise InputError(f"no usable flat pair for the gain (Eq. 16): {pair_log[0]['reason']}")
    if ptc is not None and gain_method in ("ptc", "auto"):  # "ptc" without a fit raised above
        g, g_se, g_method = ptc.g, ptc.g_stderr, _PTC_METHOD
    else:
        g, g_se, g_method = g_pairs, g_pairs_se, f"flat pairs, Eq. 16-17 (k = {k:.6f}), {len(ok_pairs)} pairs"
    if not (np.isfinite(g) and g > 0):
        raise InputError(f"gain estimate {g!r} is not positive: are the flats really flat and unsaturated?")
    rec.stderr["g"] = g_se
    rec.info["gain_method"] = g_method
    rec.info["gain_pairs"] = {"g": g_pairs, "g_stderr": g_pairs_se, "per_pair": per_pair, "k_eq17": k}
    rec.info["ptc"] = _ptc_info(ptc, x, y, sat_span)
    rec.info["ptc"]["dark_correction"] = dark_how
    for entry, in_fit in zip((e for e in pair_log if e["used"]), x <= fit_fraction * sat_span, strict=True):
        entry["ptc_fit"] = bool(in_fit and ptc is not None)
    rec.info["flat_pairs"] = pair_log
    rec.info["flat_frames"] = fl.frames
    rec.info["flat_pairs_skipped"] = fl.skipped_pairs
    rec.info["prnu_never_measured"] = fl.n_never_measured
    rec.info.setdefault("warnings", []).extend(nonlinearity_warnings(x, y, np.hypot(var_se, common_se), g, sat_span))
    if g_method != _PTC_METHOD:
        rec.info["warnings"].extend(linear_range_warnings([p.mean - ro.mu_R for p in ok_pairs], sat_span, fit_fraction))
    rec.info["flat_levels"] = [{"t": t, "level": lv, "file": nm} for t, lv, nm in fl.levels]
    rec.info["prnu_frames"] = fl.n_prnu_frames
    rec.info["prnu_rejected_samples"] = fl.n_rejected
    return g, g_se


def _ptc_info(ptc: PhotonTransferFit | None, x: np.ndarray, y: np.ndarray, sat_span: float) -> dict[str, Any]:
    """The photon-transfer points for the report (the fit's when there is one)."""
    if ptc is None:
        return {"means": x.tolist(), "variances": y.tolist(), "used": [False] * len(x), "saturation": sat_span}
    return {
        "g": ptc.g,
        "g_stderr": ptc.g_stderr,
        "means": ptc.means.tolist(),
        "variances": ptc.variances.tolist(),
        "used": ptc.used.tolist(),
        "saturation": ptc.saturation,
    }


def _dark_current_step(
    dark_fit: DarkFit | None, series: DarkSeries | None, g: float, g_se: float, sigma2_R: float, rec: _Record
) -> tuple[float, Any]:
    """D in electrons per second (clipped at 0) and the per-photosite map with its standard
    error, shrunk toward D (:func:`~.dark.shrink_dark_current_map`), from the DN/s fit."""
    if dark_fit is None or series is None:  # _dark_step returns both or neither
        return 0.0, None
    D = max(dark_fit.slope / g, 0.0)
    rec.stderr["dark_current"] = float(np.hypot(dark_fit.slope_stderr / g, D * g_se / g))
    rec.info["dark_fit"] = {
        "slope_DN_per_s": dark_fit.slope,
        "slope_stderr": dark_fit.slope_stderr,
        "intercept_DN": dark_fit.intercept,
        "D_raw_e_per_s": dark_fit.slope / g,
    }
    dmap = shrink_dark_current_map(series, g, sigma2_R, D, rec.stderr["dark_current"])
    rec.info["dark_map"] = {
        "prior_sd_e_per_s": dmap.prior_sd,
        "outlier_fraction": dmap.outlier_fraction,
        "chi2": dmap.chi2,
        "raw_negative_fraction": float(np.mean(dmap.raw < 0)),
    }
    return D, dmap


def calibrate(
    bias: Iterable,
    saturation: Iterable | None = None,
    flats: Iterable | None = None,
    darks: Iterable | None = None,
    *,
    clip: float | None = DEFAULT_CLIP,
    gain_method: str = "auto",
    white_level: float | None = None,
    fit_fraction: float = 0.7,
    dark_sink: Callable[[MasterDark], Any] | None = None,
    provenance: Mapping[str, Any] | None = None,
) -> Calibration:
    """Full Sec. 6 calibration from streamed frames.

    Order: bias (mu_R, sigma2_R, offset map) -> darks (master darks, dark current) ->
    saturation (v_sat) -> flats (PRNU map Eq. 14, gain from pairs Eq. 16-17 and from the
    photon-transfer regression). Each iterable is consumed once.

    Parameters
    ----------
    bias, saturation, flats, darks : iterable of frames
        Objects with ``data`` (2-D raw mosaic, DN), ``exposure_time`` (s) and optional
        ``path``/``white_level``, e.g. :class:`hdrcap.pipeline.io.raw.RawFrame`. Saturation
        frames and darks are optional; darks at >= 6 exposure times, ordered by time.
    clip : float or None
        Sigma-clipping threshold, standard deviations; None disables all outlier rejection.
    gain_method : {"auto", "pairs", "ptc"}
        ``auto``: the photon-transfer regression when the flats cover >= 3 exposure levels
        within ``fit_fraction`` of saturation, else the Eq. 16 pair average.
    white_level : float, optional
        ADC white level, DN: v_sat without a saturation frame; bias frames above a quarter of
        it are refused.
    fit_fraction : float
        Upper end of the photon-transfer fit range, fraction of the span bias..saturation.
    dark_sink : callable, optional
        Called as ``dark_sink(master_dark)`` for every master dark (e.g. to store it in a
        dark library) so that the masters need not stay in memory.
    provenance : mapping, optional
        Recorded with the result (camera, ISO, temperature, ...).

    Returns
    -------
    Calibration
        params (g DN/e-, mu_R DN, sigma2_R DN^2, v_sat DN, D e-/s), maps, ``stderr`` of every
        scalar and ``provenance`` (methods, frame counts, the photon-transfer and dark-series
        points for plots).

    Raises
    ------
    ValueError
        Unknown ``gain_method``.
    InputError
        Missing, inconsistent or unsuitable frames (the message names the frame).
    """
    if gain_method not in GAIN_METHODS:
        raise ValueError(f"gain_method must be auto, pairs or ptc, got {gain_method!r}")
    rec = _Record()
    ro = _readout_step(bias, clip, white_level, rec)
    dark_fit, dark_series = _dark_step(darks, ro, clip, dark_sink, rec)
    dark_slope_map = dark_series.slope_map() if dark_series is not None else None
    v_sat, sat_map = _saturation_step(saturation, white_level, ro, clip, rec)
    fl, prnu_stderr = _flat_step(flats, ro, v_sat, clip, dark_slope_map, rec)
    fl, prnu_stderr, defects = _response_defect_step(fl, prnu_stderr, ro)
    g, g_se = _gain_step(fl, ro, v_sat, dark_fit, gain_method, fit_fraction, rec)
    D, dmap = _dark_current_step(dark_fit, dark_series, g, g_se, ro.sigma2_R, rec)
    defects = _hot_defect_step(defects, dmap, rec)
    if fl.prnu_stderr is not None:
        rec.stderr["prnu_std"] = float(fl.prnu_std / np.sqrt(2 * fl.prnu.size)) if fl.prnu_std > 0 else 0.0
    prov: dict[str, Any] = dict(provenance or {})
    wl = float(white_level) if white_level is not None else float(max(v_sat, 1.0))
    params = SensorParams(
        g=float(g),
        mu_R=float(ro.mu_R),
        sigma2_R=float(ro.sigma2_R),
        v_sat=float(v_sat),
        white_level=max(wl, float(v_sat)),
        dark_current=float(D),
        name=str(prov.get("camera", "") or ""),
    )
    prov.setdefault("created", _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"))
    prov["frame_counts"] = rec.counts
    prov["n_frames"] = int(sum(rec.counts.values()))
    prov["prnu_std"] = fl.prnu_std
    prov["calibration"] = rec.info
    return Calibration(
        params=params,
        prnu=fl.prnu,
        bias_map=ro.bias_map,
        dark_current_map=None if dmap is None else dmap.rate,
        stderr={k: float(v) for k, v in rec.stderr.items()},
        provenance=prov,
        prnu_stderr=prnu_stderr,
        saturation_map=sat_map,
        bias_map_stderr=_bias_stderr_map(ro),
        dark_current_map_stderr=None if dmap is None else dmap.stderr,
        defect_map=defects,
    )


def with_file_metadata(
    calib: Calibration, meta: Mapping[str, Any], white_level: float | None = None, **changes: Any
) -> Calibration:
    """Complete a calibration with what the frame files said.

    Copies the camera model, ISO and capture timestamps the files recorded into the
    provenance (where it has none), takes the files' white level when it is above v_sat, and
    names the camera parameters after the camera.

    Parameters
    ----------
    calib : Calibration
        Result of :func:`calibrate`.
    meta : mapping
        ``camera``, ``iso``, ``first_timestamp``, ``last_timestamp``, ``white_level`` (DN),
        as read from the files (missing keys are ignored).
    white_level : float, optional
        White level given by the user, DN (wins over the files').
    **changes
        Further :class:`Calibration` fields to set.

    Returns
    -------
    Calibration
    """
    prov = dict(calib.provenance)
    for key in ("camera", "iso", "first_timestamp", "last_timestamp"):
        if meta.get(key) is not None and not prov.get(key):
            prov[key] = meta[key]
    params = calib.params
    wl = white_level or meta.get("white_level")
    if wl and wl >= params.v_sat:
        params = params.replace(white_level=float(wl))
    if prov.get("camera") and not params.name:
        params = params.replace(name=str(prov["camera"]))
    return calib.replace(provenance=prov, params=params, **changes)


def calibration_summary(
    calib: Calibration,
    *,
    output: str | os.PathLike[str] | None = None,
    seconds: float | None = None,
    emva: Any = None,
    report: Sequence[str | os.PathLike[str]] = (),
) -> dict[str, Any]:
    """The summary printed by ``hdrcap calibrate`` (one JSON line with ``--json``).

    Parameters
    ----------
    calib : Calibration
        A calibration.
    output : path, optional
        The calibration file written (entry ``output``).
    seconds : float, optional
        Run time, s (entry ``seconds``, rounded to ms).
    emva : EmvaResults, optional
        EMVA 1288 results (entry ``emva1288``).
    report : sequence of path
        Plot files written (entry ``report`` when any).

    Returns
    -------
    dict
        g (DN/e-), mu_R (DN), sigma2_R (DN^2), v_sat (DN), prnu_std (fraction), D (e-/s),
        each scalar's standard error, the frame count, the gain method, the defect counts
        (``defects``: dead, weak, hot, stuck, total; None when not measured), the shutter
        corrections (``shutter``: :func:`~.shutter.shutter_summary`, None when not measured) and
        the warnings (e.g. a non-linear photon transfer near saturation), then the entries above
        that are given.
    """
    p = calib.params
    prov = calib.provenance
    se = calib.stderr
    prnu_std = prov.get("prnu_std")
    if prnu_std is None and calib.prnu is not None:
        prnu_std = float(np.std(calib.prnu))
    summary = {
        "g": p.g,
        "g_stderr": se.get("g"),
        "mu_R": p.mu_R,
        "mu_R_stderr": se.get("mu_R"),
        "sigma2_R": p.sigma2_R,
        "sigma2_R_stderr": se.get("sigma2_R"),
        "v_sat": p.v_sat,
        "v_sat_stderr": se.get("v_sat"),
        "prnu_std": prnu_std,
        "dark_current": p.dark_current,
        "dark_current_stderr": se.get("dark_current"),
        "n_frames": prov.get("n_frames"),
        "gain_method": prov.get("calibration", {}).get("gain_method"),
        "defects": prov.get("calibration", {}).get("defects", {}).get("counts"),
        "shutter": None if calib.shutter is None else shutter_summary(calib.shutter),
        "warnings": list(prov.get("calibration", {}).get("warnings", [])),
    }
    if output is not None:
        summary["output"] = str(output)
    if seconds is not None:
        summary["seconds"] = round(seconds, 3)
    if emva is not None:
        summary["emva1288"] = emva.to_dict()
    if report:
        summary["report"] = [str(r) for r in report]
    return summary


def format_summary(summary: Mapping[str, Any]) -> str:
    """The summary as text: g, mu_R, sigma2_R, v_sat, D, the PRNU and the defects on one line,
    the shutter table (one line per time), then one line per warning.

    Parameters
    ----------
    summary : mapping
        Output of :func:`calibration_summary`.

    Returns
    -------
    str
    """
    s = summary
    return (
        f"g = {s['g']:.5g} ± {s['g_stderr']:.2g} DN/e-  mu_R = {s['mu_R']:.4g} DN  "
        f"sigma2_R = {s['sigma2_R']:.4g} DN^2  v_sat = {s['v_sat']:.5g} DN  "
        f"D = {s['dark_current']:.3g} e-/s  PRNU = {100 * (s['prnu_std'] or 0):.3g} %"
        + _defect_text(s)
        + _shutter_text(s)
        + "".join(f"\nwarning: {w}" for w in s.get("warnings") or ())
    )


def _defect_text(summary: Mapping[str, Any]) -> str:
    """``  defects: N (dead a, weak b, hot c, stuck d)`` when the summary has defect counts."""
    c = summary.get("defects")
    if not c:
        return ""
    return f"  defects: {c['total']} ({', '.join(f'{k} {c[k]}' for k in DEFECT_BITS)})"


def _shutter_text(summary: Mapping[str, Any]) -> str:
    """The shutter table, a header line and one line per time, when the summary has one."""
    sh = summary.get("shutter")
    if not sh:
        return ""
    jitter = "not measured" if sh["jitter"] is None else f"{100 * sh['jitter']:.2g} %"
    lines = [f"\nshutter: t_eff/t_nom relative to {sh['reference']:g} s (frame jitter {jitter})"]
    for e in sh["times"]:
        lines.append(f"\n  {e['t']:<10.4g} s  {e['factor']:.5f} ± {100 * e['stderr']:.2g} %  ({e['frames']} frames)")
    return "".join(lines)
