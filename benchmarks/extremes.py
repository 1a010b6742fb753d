"""Numerical stability of the merge at the extremes: a sweep over bracket spacing, bit depth, clipping,
exposure time and saturation model; prints one JSON object (``--docs``: also updates the table of
docs/merge.md, *Stability at the extremes*).

The sweep's cases:

* cameras (:func:`hdrcap.experiments.extremes.cameras`): 8-, 10-, 12-, 14- and 16-bit, each once with the full well clipping
  before the ADC (``fw``: saturated values scatter around v_sat + 3 sigma_R, some slip under
  v_sat on read noise) and once with the ADC clipping first (``adc``: saturated values are the
  white level). The dark current is 30 % of the full well over 3600 s (30 % DCNU), so that it
  dominates the signal of the darker photosites in the long exposures;
* brackets (:func:`bracket_times`): spacing x1.25, x2, x4, x10 and x100, at most 16 frames,
  starting at 1e-6 s (``up``) or ending at 3600 s (``down``), matched dark frames;
* scenes over 8 decades: half the photosites log-uniform from 3 times the shortest exposure's
  clip level down by 1e8 (the scene), half placed uniformly in k in [-4, 4] around the clip
  level of a random exposure, k = (E v - v_sat)/sd(v) (for the bands of k);
* both saturation models (``threshold``, ``probabilistic``);
* calibrations estimated from simulated calibration frames of each sensor
  (``hdrcap.experiments.calibrated.estimated_calibration``: 2 bias frames, 1 saturation frame, 16 flats, a dark
  series at 1-32 s), never the simulator's truth.

Per case (seeds pooled) z = (estimate - truth)/sigma, the truth scaled by the estimated gain's
error (an error common to every photosite, reported in the header, not in sigma), over the
photosites with an estimate (nexp > 0): per decade of the scene (log10 X/X_max in -8..0, the
log-uniform half) and per
band of k of the nearest clip level (all photosites; within 3 sigma of the shortest exposure's
clip level left out of both: above it only a lower bound exists), the count,
z mean and spread, the fraction beyond 6 sigma, the photosites beyond 8 sigma without a quality
bit (all photosites), and the non-finite outputs. ``pass_decades`` (the issue's criterion):
every irradiance decade with >= 200 photosites (:data:`MIN_BAND`) has |z mean| <= 0.1 and
0.85 <= z spread <= 1.15, no photosite beyond 8 sigma is unflagged and no output is
non-finite; ``pass``: the same and every band of k too.

Usage::

    python benchmarks/extremes.py [--size 64] [--seeds 16] [--docs] [--camera 14-bit-fw ...]
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from hdrcap.experiments.calibrated import estimated_calibration
from hdrcap.experiments.extremes import T_MAX, T_MIN, cameras, nearest_clip
from hdrcap.pipeline.schema import QUALITY_BITS

REPO = Path(__file__).resolve().parents[1]

#: Bracket spacings (ratio of consecutive exposure times).
SPACINGS = (1.25, 2.0, 4.0, 10.0, 100.0)
MAX_FRAMES = 16
SATURATIONS = ("threshold", "probabilistic")
K_EDGES = (-3, -2, -1, 0, 1, 2, 3)
#: A band is judged when it holds at least this many photosites.
MIN_BAND = 200
#: The targets of a judged band.
TARGET_MEAN, TARGET_STD = 0.1, (0.85, 1.15)
DOCS_BEGIN, DOCS_END = "<!-- extremes:begin -->", "<!-- extremes:end -->"


def bracket_times(spacing: float, anchor: str) -> list[float]:
    """Exposure times (s), shortest first: ``spacing`` apart, at most :data:`MAX_FRAMES`, within
    1e-6..3600 s, starting at 1e-6 s (``up``) or ending at 3600 s (``down``)."""
    n = min(MAX_FRAMES, int(math.floor(math.log(T_MAX / T_MIN) / math.log(spacing) + 1e-9)) + 1)
    if anchor == "up":
        return [T_MIN * spacing**i for i in range(n)]
    return [T_MAX / spacing ** (n - 1 - i) for i in range(n)]


def _electrons_at_k(spec, v_sat: float, k: np.ndarray) -> np.ndarray:
    """Electrons E with mu_R + g E = v_sat + k sqrt(g^2 E + sigma2_R) (fixed point)."""
    e = np.full(k.shape, (v_sat - spec.mu_R) / spec.g)
    for _ in range(12):
        e = (v_sat + k * np.sqrt(spec.g**2 * np.maximum(e, 0.0) + spec.sigma2_R) - spec.mu_R) / spec.g
    return np.maximum(e, 0.0)


def x_max(spec, times) -> float:
    """The top of the log-uniform scene: 3 times the shortest exposure's clip level, e-/s."""
    return 3.0 * (spec.nominal_params().v_sat - spec.mu_R) / (spec.g * min(times))


def scene(sensor, times, rng) -> tuple[np.ndarray, np.ndarray]:
    """Irradiance, e-/s: half log-uniform over 8 decades below 3 times the shortest exposure's
    clip level, half at k ~ U(-4, 4) around the clip level of a random exposure (the true PRNU
    and dark-current map); and the mask of the latter."""
    spec = sensor.spec
    shape = sensor.prnu.shape
    v_sat = spec.nominal_params().v_sat
    dark = sensor.dark_current_map()
    a = np.maximum(sensor.prnu, 1e-3)
    X = x_max(spec, times) * 10.0 ** rng.uniform(-8.0, 0.0, shape)
    near = rng.random(shape) < 0.5
    t = np.asarray(times)[rng.integers(0, len(times), shape)]
    e = _electrons_at_k(spec, v_sat, rng.uniform(-4.0, 4.0, shape))
    Xk = (e / t - dark) / a
    ok = near & (Xk > 0)
    X[ok] = Xk[ok]
    return X, ok


def _band(z: np.ndarray, flagged: np.ndarray) -> dict[str, Any]:
    n = int(z.size)
    out: dict[str, Any] = {"n": n}
    if n == 0:
        return out
    out.update(
        mean=float(z.mean()),
        std=float(z.std()),
        beyond6=float(np.mean(np.abs(z) > 6)),
        beyond8_unflagged=int(np.count_nonzero((np.abs(z) > 8) & ~flagged)),
    )
    if n >= MIN_BAND:
        out["ok"] = bool(abs(out["mean"]) <= TARGET_MEAN and TARGET_STD[0] <= out["std"] <= TARGET_STD[1])
    return out


def judge(z, flagged, lx, k, shortest, placed) -> dict[str, Any]:
    """Bands of one case: the scene's 8 decades of ``lx`` = log10(X / X_max) over the
    log-uniform scene (not the photosites ``placed`` at the clip levels), and bands of ``k`` (the nearest clip
    level) over all. Photosites within 3 sigma of the shortest exposure's clip level
    (``shortest``) are left out of both: above it no sample measures X, and those that keep an
    estimate there are a selection by their own noise (biased whatever the estimator)."""
    decades = {}
    top = shortest & (np.abs(k) < 3)
    for lo in range(-8, 0):
        m = ~top & ~placed & (lx >= lo) & (lx < lo + 1)
        decades[f"{lo:+d}..{lo + 1:+d}"] = _band(z[m], flagged[m])
    kb = {}
    for lo, hi in zip(K_EDGES[:-1], K_EDGES[1:]):
        m = ~shortest & (k >= lo) & (k < hi)
        kb[f"{lo:+d}..{hi:+d}"] = _band(z[m], flagged[m])
    return {"decades": decades, "k_bands": kb}


def _false_rejections(sensor, cal, X, times, frames, quality) -> int:
    """Photosites the clip rule flagged although none of their samples in its window can be a
    clipped value: every such sample's expected electrons (the truth) lie more than 6 of
    their standard deviations below the full well."""
    hit = (quality & QUALITY_BITS["clip_rejected"]) != 0
    if not hit.any():
        return 0
    spec = sensor.spec
    p = cal.params
    window = p.v_sat - 3.0 * np.sqrt(p.g * (p.v_sat - p.mu_R) + p.sigma2_R)
    rate = (sensor.prnu * X + sensor.dark_current_map())[hit]
    maybe = np.zeros(rate.shape, bool)
    for t, f in zip(times, frames):
        v = f[hit].astype(np.float64)
        e = rate * t
        maybe |= (v >= window) & (v < p.v_sat) & (e > spec.full_well - 6.0 * np.sqrt(spec.full_well))
    return int(np.count_nonzero(~maybe))


def run_case(spec, seeds: int, size: int, spacing: float, anchor: str, cals: dict) -> dict[str, Any]:
    """Both saturation models on one camera and bracket, ``seeds`` sensors pooled."""
    from hdrcap.mock_camera.sensor import SimulatedSensor
    from hdrcap.pipeline.merge.accumulator import merge_arrays

    times = bracket_times(spacing, anchor)
    pooled: dict[str, dict[str, list]] = {s: {} for s in SATURATIONS}
    counts = {s: {"nonfinite": 0, "seconds": 0.0, "info": {}} for s in SATURATIONS}
    for seed in range(1, seeds + 1):
        key = (spec.name, seed)
        if key not in cals:
            sensor = SimulatedSensor(spec, (size, size), seed=1000 + seed)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                cals[key] = (sensor, estimated_calibration(sensor, np.random.default_rng([seed, 71])))
        sensor, cal = cals[key]
        rng = np.random.default_rng([seed, 73, int(spacing * 100), anchor == "up"])
        X, placed = scene(sensor, times, rng)
        frames = [sensor.expose(X, t, rng=rng) for t in times]
        darks = [sensor.expose(X, t, dark=True, rng=rng) for t in times]
        k, which = nearest_clip(sensor, X, times, spec.nominal_params().v_sat)
        truth = X * spec.g / cal.params.g
        for sat in SATURATIONS:
            t0 = time.perf_counter()
            res = merge_arrays(frames, times, cal, darks, saturation=sat)
            counts[sat]["seconds"] += time.perf_counter() - t0
            arrays = (res.irradiance, res.sigma, res.nexp) + (
                () if res.sigma_calibration is None else (res.sigma_calibration,)
            )
            counts[sat]["nonfinite"] += int(sum(np.count_nonzero(~np.isfinite(a)) for a in arrays))
            for name in ("clip_rejected", "clip_rejected_samples", "censored_fallback", "saturated_everywhere"):
                if res.info.get(name) is not None:
                    counts[sat]["info"][name] = counts[sat]["info"].get(name, 0) + int(res.info[name])
            if res.quality is not None:
                counts[sat]["info"]["clip_rejected_unclipped"] = counts[sat]["info"].get(
                    "clip_rejected_unclipped", 0
                ) + _false_rejections(sensor, cal, X, times, frames, res.quality)
            ok = (res.nexp > 0) & (res.sigma > 0)
            z = (res.irradiance.astype(np.float64) - truth)[ok] / res.sigma[ok]
            q = res.quality if res.quality is not None else np.zeros(X.shape, np.uint8)
            parts = pooled[sat]
            for name, arr in (
                ("z", z),
                ("flagged", q[ok] != 0),
                ("lx", np.log10(X[ok] / x_max(spec, times))),
                ("k", k[ok]),
                ("shortest", (which == 0)[ok]),
                ("placed", placed[ok]),
            ):
                parts.setdefault(name, []).append(arr)
    out: dict[str, Any] = {"camera": spec.name, "spacing": spacing, "anchor": anchor, "times": times}
    for sat in SATURATIONS:
        cat = {name: np.concatenate(v) for name, v in pooled[sat].items()}
        bands = judge(cat["z"], cat["flagged"], cat["lx"], cat["k"], cat["shortest"], cat["placed"])
        judged = [b for part in bands.values() for b in part.values() if "ok" in b]
        unflagged = int(np.count_nonzero((np.abs(cat["z"]) > 8) & ~cat["flagged"]))  # every photosite
        nonfinite = counts[sat]["nonfinite"]
        out[sat] = {
            **bands,
            "photosites": int(cat["z"].size),
            "nonfinite": nonfinite,
            "beyond8_unflagged": unflagged,
            "max_abs_z": float(np.abs(cat["z"]).max()) if cat["z"].size else None,
            "counts": counts[sat]["info"],
            "merge_seconds": round(counts[sat]["seconds"], 3),
            "pass_decades": all(b["ok"] for b in bands["decades"].values() if "ok" in b)
            and unflagged == 0
            and nonfinite == 0,
            "pass": all(b["ok"] for b in judged) and unflagged == 0 and nonfinite == 0,
        }
    return out


def sweep(seeds: int = 16, size: int = 64, names=None, spacings=SPACINGS, anchors=("up", "down")) -> dict[str, Any]:
    """Every case of the sweep (see the module docstring)."""
    specs = cameras()
    cals: dict = {}
    t0 = time.perf_counter()
    cases = [
        run_case(specs[name], seeds, size, s, a, cals)
        for name in (names or list(specs))
        for s in spacings
        for a in anchors
    ]
    return {
        "settings": {"seeds": seeds, "size": size, "min_band": MIN_BAND, "darks": "matched"},
        "seconds": round(time.perf_counter() - t0, 1),
        "cases": cases,
        "all_pass": all(c[s]["pass"] for c in cases for s in SATURATIONS),
        "all_pass_decades": all(c[s]["pass_decades"] for c in cases for s in SATURATIONS),
    }


def _worst(case: dict, part: str) -> tuple[float, float, float]:
    """Worst |z mean| and the z spread range over the judged bands of ``part``."""
    bands = [b for b in case[part].values() if b.get("n", 0) >= MIN_BAND]
    if not bands:
        return math.nan, math.nan, math.nan
    worst = max(bands, key=lambda b: abs(b["mean"]))["mean"]
    return worst, min(b["std"] for b in bands), max(b["std"] for b in bands)


def _cell(case: dict, sat: str) -> str:
    c = case[sat]
    cells = []
    for part in ("decades", "k_bands"):
        m, lo, hi = _worst(c, part)
        cells.append("—" if math.isnan(m) else f"{m:+.2f} / {lo:.2f}–{hi:.2f}")
    mark = " ✗" if not c["pass_decades"] else ("" if c["pass"] else " (k)")
    return f"{cells[0]}; {cells[1]}; {c['beyond8_unflagged']}{mark}"


def markdown(result: dict[str, Any]) -> str:
    """One row per camera and saturation model, one column per spacing (the two anchors of a
    spacing in one cell, ``up`` then ``down``)."""
    cases = result["cases"]
    spacings = sorted({c["spacing"] for c in cases})
    lines = [
        "| camera | saturation | " + " | ".join(f"x{s:g}" for s in spacings) + " |",
        "|---|---|" + "---|" * len(spacings),
    ]
    for name in dict.fromkeys(c["camera"] for c in cases):
        for sat in SATURATIONS:
            cells = []
            for s in spacings:
                here = [c for c in cases if c["camera"] == name and c["spacing"] == s]
                cells.append("<br>".join(_cell(c, sat) for c in here))
            lines.append(f"| {name} | {sat} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def update_docs(table: str, path: Path = REPO / "docs" / "merge.md") -> None:
    """Replace the table between the markers of docs/merge.md."""
    text = path.read_text()
    pattern = re.compile(re.escape(DOCS_BEGIN) + r".*?" + re.escape(DOCS_END), re.S)
    if not pattern.search(text):
        raise SystemExit(f"{path}: no {DOCS_BEGIN} ... {DOCS_END} markers")
    path.write_text(pattern.sub(lambda _: f"{DOCS_BEGIN}\n{table}\n{DOCS_END}", text))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=16, help="sensors per camera (default 16)")
    ap.add_argument("--size", type=int, default=64, help="mosaic side, photosites (default 64)")
    ap.add_argument("--camera", action="append", choices=list(cameras()), help="only these cameras")
    ap.add_argument("--spacing", action="append", type=float, help="only these spacings")
    ap.add_argument("--markdown", action="store_true", help="print the docs table after the JSON")
    ap.add_argument("--docs", action="store_true", help="write the table into docs/merge.md")
    args = ap.parse_args(argv)
    result = sweep(args.seeds, args.size, args.camera, tuple(args.spacing or SPACINGS))
    print(json.dumps(result, indent=1))
    table = markdown(result)
    if args.markdown:
        print(table)
    if args.docs:
        update_docs(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
