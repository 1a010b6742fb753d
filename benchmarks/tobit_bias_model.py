"""An independent model of the censored (Tobit) merge near a clip level, in units of the censored
sample's standard deviation: one sample y1 ~ N(theta, 1) censored at 0 (only "y1 >= 0" is kept
when it is), and the shorter exposures summarised as one Gaussian y0 ~ N(theta, 1/r) with r
times the censored sample's information (about 0.32 for exposures a factor 4 apart; 0.15-0.25
fits camera-B's residuals better). k = theta.

Per k, z = (estimate - theta)/sigma (mean / spread) of:

* ``ml``: the censored likelihood's root, sigma from the observed information (what the merge
  did before the centring);
* ``cox-snell``: the root minus its first-order bias (kappa_{11,1} + kappa_111/2)/I^2;
* ``firth``: the root of the score plus (1/2) d log I/d theta (Jeffreys-penalised likelihood);
* ``centred``: the root minus kappa_{11,1}/(2 I^2), the first-order mean of the Wald statistic
  times sigma (what the merge does now, ``pipeline.merge.kernels._tobit``);

and ``bias``: the estimate's own mean error in units of 1/sqrt(I(theta)). Numpy and scipy only
(nothing of hdrcap), one seed.

Usage: python benchmarks/tobit_bias_model.py [--ratio 0.32] [--n 100000] [--markdown]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from scipy.special import log_ndtr, ndtr

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)


def _phi(u):
    return np.exp(-0.5 * u * u - _LOG_SQRT_2PI)


def _mills(u):
    """phi(u)/(1 - Phi(u))."""
    return np.exp(-0.5 * u * u - _LOG_SQRT_2PI - log_ndtr(-u))


def _moments(theta, r):
    """Expected information I, kappa_{11,1} = E[l'' l'] and kappa_111 = E[l''']."""
    u = -theta
    lam = _mills(u)
    phi = _phi(u)
    info = r + ndtr(u) + phi * (lam - u)
    k11_1 = phi * (1.0 - lam * (lam - u))
    k111 = phi * ((lam - u) * (2.0 * lam - u) - 1.0)
    return info, k11_1, k111


def _root(f, n, steps=60):
    lo, hi = np.full(n, -40.0), np.full(n, 40.0)
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        pos = f(mid) > 0
        lo, hi = np.where(pos, mid, lo), np.where(pos, hi, mid)
    return 0.5 * (lo + hi)


def run(k: float, r: float, n: int, rng: np.random.Generator) -> dict:
    """z mean and spread of each estimator at theta = k.

    Parameters
    ----------
    k : float
        theta, the censored sample's mean minus the censoring point, in its sd.
    r : float
        Information of the uncensored part relative to the censored sample's.
    n : int
        Replications.
    rng : numpy.random.Generator
        The noise.

    Returns
    -------
    dict
        Estimator name -> {"z_mean", "z_spread", "bias"}.
    """
    y0 = k + rng.standard_normal(n) / np.sqrt(r)
    y1 = k + rng.standard_normal(n)
    cen = y1 >= 0.0

    def score(t):
        return r * (y0 - t) + np.where(cen, _mills(-t), y1 - t)

    ml = _root(score, n)
    sigma = 1.0 / np.sqrt(r + np.where(cen, _mills(-ml) * (_mills(-ml) + ml), 1.0))  # observed information
    info, k11_1, k111 = _moments(ml, r)
    eps = 1e-5
    firth = _root(
        lambda t: score(t) + 0.25 * (np.log(_moments(t + eps, r)[0]) - np.log(_moments(t - eps, r)[0])) / eps, n
    )
    est = {
        "ml": ml,
        "cox-snell": ml - (k11_1 + 0.5 * k111) / info**2,
        "firth": firth,
        "centred": ml - 0.5 * k11_1 / info**2,
    }
    i_true = _moments(np.float64(k), r)[0]
    out = {}
    for name, e in est.items():
        z = (e - k) / sigma
        out[name] = {
            "z_mean": round(float(z.mean()), 3),
            "z_spread": round(float(z.std()), 3),
            "bias": round(float((e - k).mean() * np.sqrt(i_true)), 3),
        }
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--ratio", type=float, default=0.32, help="information of the shorter exposures / the censored one's"
    )
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(1)
    ks = np.arange(-3.0, 3.01, 0.5)
    result = {f"{k:+.1f}": run(k, args.ratio, args.n, rng) for k in ks}
    if not args.markdown:
        print(json.dumps({"ratio": args.ratio, "n": args.n, "k": result}, indent=1))
        return
    names = list(next(iter(result.values())))
    print(f"r = {args.ratio}: z mean / z spread (estimate's bias in 1/sqrt(I) units)\n")
    print("| k | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    for k, row in result.items():
        cells = [f"{row[m]['z_mean']:+.3f} / {row[m]['z_spread']:.2f} ({row[m]['bias']:+.2f})" for m in names]
        print(f"| {k} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
