"""The errors a merge's estimate shares across its exposures: the calibration's and a master dark's.

Per photosite, after the iterations: the first-order propagation of the standard errors of the
calibration's bias, dark-current and PRNU maps (``sigma_calibration``), and the noise of one
master dark taken at a known time and shared by every frame extrapolated from it. Both are
independent of the per-sample noise the kernel's sigma holds and are added to it in quadrature
(:func:`add_in_quadrature`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hdrcap.pipeline.merge.kernel_inputs import KernelInputs
from hdrcap.pipeline.merge.options import MergeOptions
from hdrcap.pipeline.params import Calibration

__all__ = ["ErrorTerm", "calibration_errors", "shared_terms", "add_in_quadrature"]

#: A standard error as a float32 map or a scalar (0: unknown).
ErrorTerm = np.ndarray | float


def calibration_errors(
    calibration: Calibration, prnu_used: str
) -> tuple[ErrorTerm, ErrorTerm, ErrorTerm, dict[str, Any]]:
    """The standard errors of the calibration quantities a merge uses.

    Without a bias map the photosite's offset is taken as mu_R: its error is the offset
    non-uniformity (``bias_dsnu_DN`` of the calibration) with the error of mu_R. With
    ``prnu="scalar"`` (a = 1) the error of a_j is the PRNU spread itself (``prnu_std``).

    Parameters
    ----------
    calibration : Calibration
        Camera model, maps, their standard errors and provenance.
    prnu_used : {"map", "scalar"}
        Which PRNU the merge uses.

    Returns
    -------
    (ErrorTerm, ErrorTerm, ErrorTerm, dict)
        Standard errors of the bias level (DN), the dark current (e-/s) and the PRNU gain a_j
        (dimensionless), as float32 maps or scalars (0: unknown); and the description recorded
        in the header (``included``, ``missing``, ``gain_relative_stderr``, ``note``).
    """
    cal = calibration
    se = cal.stderr or {}
    prov = cal.provenance or {}
    used: list[str] = []
    missing: list[str] = []

    def pick(name: str, map_: np.ndarray | None, scalar: float | None) -> ErrorTerm:
        if map_ is not None:
            used.append(f"{name} map")
            return np.asarray(map_, np.float32)
        if scalar is not None and np.isfinite(scalar) and scalar > 0:
            used.append(name)
            return float(scalar)
        missing.append(name)
        return 0.0

    if cal.bias_map is not None:
        s_b = pick("bias", cal.bias_map_stderr, None)
    else:
        dsnu = (prov.get("calibration") or {}).get("bias_dsnu_DN")
        s_b = pick("bias", None, math.hypot(float(se.get("mu_R", 0.0)), float(dsnu or 0.0)) or None)
    if cal.dark_current_map is not None:
        s_d = pick("dark current", cal.dark_current_map_stderr, None)
    else:
        s_d = pick("dark current", None, se.get("dark_current"))
    if prnu_used == "map":
        s_a = pick("PRNU", cal.prnu_stderr, None)
    else:
        s_a = pick("PRNU spread (prnu scalar)", None, prov.get("prnu_std"))
    desc = {
        "included": used,
        "missing": missing,
        "gain_relative_stderr": float(se.get("g", 0.0)) / float(cal.params.g),
        "note": "sigma includes the calibration's per-photosite error (sigma_calibration); the gain's "
        "relative error is common to every photosite and not included",
    }
    return s_b, s_d, s_a, desc


def shared_terms(
    irr: np.ndarray,
    nexp: np.ndarray,
    rules: np.ndarray,
    inputs: KernelInputs,
    timed_master: np.ndarray,
    calibration: Calibration,
    prnu_used: str,
    options: MergeOptions,
) -> tuple[np.ndarray | None, np.ndarray | None, dict[str, Any]]:
    """The errors common to all exposures of a photosite, propagated to X at the estimate.

    Propagated with the weights (Eq. 13) of the samples the merge kept (Eq. 11 and the
    near-saturation rule, evaluated at the final estimate; with the censored likelihood of
    ``saturation="probabilistic"`` every sample with its share of the information,
    1/Var(x_i) below v_sat and lambda(z) (lambda(z) - z)/Var(x_i) at or above it, z the clip
    level's distance in standard deviations: the censored estimate moves with a shift of the
    dark level of sample i by -(this)/(t g a) over the sum, as the threshold model's does with
    its weights; a photosite where the censored likelihood fell back to the threshold estimate
    takes the threshold model's weights):

    * sigma_calibration: the first-order propagation of the standard errors of the
      calibration's bias, dark-current and PRNU maps (:func:`calibration_errors`);
    * the noise of one master dark taken at t_ref and shared by every frame extrapolated
      from it: d mu / d M = -sum_i w_i / (t_i g a) / W over those frames, variance
      (g^2 t_ref D + sigma_R^2)/N.

    Computed per photosite by :func:`pipeline.merge.kernels.calibration_terms_kernel` (parallel
    over rows) from the merge kernel's own inputs (the dark-current coefficient of a frame
    with its own dark frame is 0).

    Parameters
    ----------
    irr, nexp : numpy.ndarray
        The merge kernel's irradiance (e-/s) and usable-sample counts, float32.
    rules : numpy.ndarray
        The merge kernel's rule bits per photosite, uint8
        (:attr:`pipeline.merge.kernels.MergeOutputs.rules`).
    inputs : KernelInputs
        The merge kernel's inputs.
    timed_master : numpy.ndarray
        bool per frame: its dark level is the single master dark taken at ``master_dark_time``
        (:meth:`pipeline.merge.frames.FrameBook.shares_timed_master`).
    calibration : Calibration
        Camera model with the standard errors of its maps.
    prnu_used : {"map", "scalar"}
        Which PRNU the merge uses.
    options : MergeOptions
        The merge's options (saturation model and margin, master dark's time and N).

    Returns
    -------
    (numpy.ndarray or None, numpy.ndarray or None, dict)
        sigma_calibration (None when ``desc["included"]`` is empty: the calibration's part
        is unknown, not zero) and the master dark's term (None when no frame shares a timed
        master dark), e-/s, float32; the description of the calibration's errors.
    """
    s_b, s_d, s_a, desc = calibration_errors(calibration, prnu_used)
    out = np.zeros(irr.shape, np.float32) if desc["included"] else None
    master_used = timed_master.astype(np.float64)
    out_m = np.zeros(irr.shape, np.float32) if master_used.any() else None
    if out is None and out_m is None:
        return out, out_m, desc
    _run_terms_kernel(irr, nexp, rules, inputs, (s_b, s_d, s_a), master_used, options, out, out_m)
    return out, out_m, desc


def _run_terms_kernel(
    irr: np.ndarray,
    nexp: np.ndarray,
    rules: np.ndarray,
    inputs: KernelInputs,
    errors: tuple[ErrorTerm, ErrorTerm, ErrorTerm],
    master_used: np.ndarray,
    options: MergeOptions,
    out: np.ndarray | None,
    out_m: np.ndarray | None,
) -> None:
    """Fill ``out`` (sigma_calibration) and ``out_m`` (the master dark's term), those not None,
    with :func:`pipeline.merge.kernels.calibration_terms_kernel` from the calibration's
    standard ``errors`` (bias, dark current, PRNU) and the frames sharing the timed master dark
    (``master_used``, 1.0 per such frame)."""
    from hdrcap.pipeline.merge.kernels import (
        ErrorMaps,
        MapArg,
        SharedTerms,
        calibration_terms_kernel,
        reflected_lists_quiet,
    )

    frames = inputs.frames
    bias_used = (frames.kinds == 1).astype(np.float64)
    # Only frames whose dark level comes from the calibration's maps need their weights.
    needs_weights = bool(np.any(bias_used > 0) or np.any(frames.coefs != 0) or master_used.any())
    t_ref = options.master_dark_time

    # the output not asked for gets a placeholder: the other one
    first, second = (out if out is not None else out_m), (out_m if out_m is not None else out)
    assert first is not None and second is not None  # at least one is asked for (shared_terms)

    def err_arg(e: ErrorTerm) -> MapArg:
        return MapArg(e, True, 0.0) if isinstance(e, np.ndarray) else MapArg(np.zeros((1, 1), np.float32), False, e)

    with reflected_lists_quiet():
        calibration_terms_kernel(
            *inputs,
            ErrorMaps(*(err_arg(e) for e in errors)),
            SharedTerms(
                np.ascontiguousarray(np.stack([bias_used, master_used], axis=1)),
                float(options.saturation_sigmas) ** 2,
                options.saturation == "probabilistic",
                needs_weights,
                out is not None,
                out_m is not None,
                float(t_ref) if t_ref is not None else 0.0,
                float(options.n_dark),
            ),
            irr,
            nexp,
            rules,
            first,
            second,
        )


def add_in_quadrature(sigma: np.ndarray, *terms: np.ndarray | None, rows: int = 256) -> None:
    """sigma = sqrt(sigma^2 + sum of terms^2), in place, in float64 (the total uncertainty of
    independent error sources), a block of ``rows`` rows at a time (no full-size float64
    temporaries). Without terms it is |sigma| (sqrt of an exact float64 square: the same
    bits).

    Parameters
    ----------
    sigma : numpy.ndarray
        float32 standard uncertainties (any unit), 2-D; overwritten.
    *terms : numpy.ndarray or None
        Further standard uncertainties of the same shape and unit; None entries are skipped.
    rows : int
        Rows per block.
    """
    given = [t for t in terms if t is not None]
    if not given:
        np.abs(sigma, out=sigma)
        return
    for r0 in range(0, sigma.shape[0], rows):
        sl = slice(r0, r0 + rows)
        total = np.square(sigma[sl], dtype=np.float64)
        for t in given:
            total += np.square(t[sl], dtype=np.float64)
        np.sqrt(total, out=sigma[sl], casting="unsafe")
