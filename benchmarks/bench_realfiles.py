"""What self-calibration identifies on real-camera-like files; prints one JSON object.

Seven brackets of one simulated machine-vision camera (a 12-bit ADC whose frames are saved as
8-bit TIFF, im2uint8-style; 0.09 DN/e- in 8-bit DN, read noise 5 e-, black 6.23 DN (8-bit),
1 % PRNU, Bayer GBRG), each of another scene and level, seven exposures 25 ms to 3.9 s, are
self-calibrated from the files alone (``--cfa GBRG``). Reported per bracket: the gain with its
stated standard error, the read-noise variance used, the reduced chi^2 of the photon-transfer
fit over its degrees of freedom, the black level estimated from the bracket; and across the
brackets the weighted mean gain and chi^2/dof of the gains about it (consistency: <= 4 means
they agree within their stated errors). The same brackets with the black level taken as 0 DN
(what a PNG/TIFF gave before the black level was estimated) show what a wrong model does: the
fit's chi^2 rejects it and the stated errors grow. With the EMVA 1288 reference set 001 on the
machine (``../shared/datasets/emva1288-ref001`` or ``$HDRCAP_EMVA_REF001``), a bracket of its
flat fields is self-calibrated too and compared with the standard's gain K.

Usage: python benchmarks/bench_realfiles.py [--size WxH] [--seed N] [--out DIR]
docs/selfcal.md quotes its figures.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hdrcap.experiments.realfiles import BRACKET_SCENES, G8, MV, TIMES, bracket_frames, scene

EMVA_K = 0.280769280926  # DN/e-, the reference set's published gain


def _consistency(rows: list[dict]) -> dict:
    est = [r for r in rows if r["gain_estimated"]]
    if len(est) < 2:
        return {"brackets_estimated": len(est)}
    g = np.array([r["gain"] for r in est])
    s = np.array([r["gain_stderr"] for r in est])
    mean = float(np.sum(g / s**2) / np.sum(1 / s**2))
    return {
        "brackets_estimated": len(est),
        "weighted_mean_gain": round(mean, 5),
        "mean_relative_error_vs_truth": round(mean / G8 - 1, 4),
        "chi2_per_dof_between_brackets": round(float(np.sum(((g - mean) / s) ** 2) / (len(g) - 1)), 2),
        "smallest_relative_stderr": float(np.min(s / g)),
    }


def _row(sc) -> dict:
    head = sc.header()
    fit, gain = head["photon_transfer_fit"], head["gain"]
    row = {
        "gain_estimated": sc.gain_known,
        "gain": round(sc.fit["g"], 5),
        "gain_stderr": None if sc.fit["g_stderr"] is None else float(f"{sc.fit['g_stderr']:.3g}"),
        "sigma2_R_used": round(sc.calibration.params.sigma2_R, 4),
        "reduced_chi2": round(fit.get("reduced_chi2", float("nan")), 2),
        "dof": fit.get("dof"),
        "model_rejected": fit.get("model_rejected"),
        "relative_misfit": round(fit.get("relative_misfit", float("nan")), 3),
        "black_level": sc.black_source,
    }
    if not sc.gain_known:
        row["gain_fitted"] = None if gain.get("fitted") is None else round(gain["fitted"], 5)
        row["not_estimable"] = gain.get("not_estimable")
    return row


def brackets(folder: Path, shape: tuple[int, int], seed: int) -> dict:
    """The seven brackets written as 8-bit TIFF and self-calibrated, black level estimated and
    taken as 0 DN."""
    import dataclasses

    from hdrcap.mock_camera.sensor import SimulatedSensor
    from hdrcap.pipeline.calibration.selfcal import self_calibrate

    sensor = SimulatedSensor(MV, shape, seed=seed)
    estimated, zero = [], []
    for k, (name, decades, level) in enumerate(BRACKET_SCENES):
        X = scene(shape, name, decades, level)
        frames = bracket_frames(sensor, X, folder, f"b{k}", np.random.default_rng([seed, 28, k]))
        estimated.append({"scene": f"{name} {decades:g} decades x{level:g}", **_row(self_calibrate(frames))})
        zero.append(_row(self_calibrate([dataclasses.replace(f, black_level=0.0) for f in frames])))
    return {
        "black_level_estimated": {"brackets": estimated, "consistency": _consistency(estimated)},
        "black_level_taken_as_0": {"brackets": zero, "consistency": _consistency(zero)},
    }


def emva() -> dict | None:
    """A bracket of the EMVA 1288 reference set's flat fields (--bits 12, black 14.7 DN)."""
    env = os.environ.get("HDRCAP_EMVA_REF001")
    root = Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "datasets" / "emva1288-ref001"
    if not (root / "EMVA1288_Data.txt").is_file():
        return None
    from hdrcap.pipeline.calibration.selfcal import self_calibrate
    from hdrcap.pipeline.io.frameformat import FrameFormat
    from hdrcap.pipeline.io.raw import read_frame

    steps: list[tuple[float, Path]] = []
    kind, first, t = None, False, 0.0
    for line in (root / "EMVA1288_Data.txt").read_text().splitlines():
        p = line.split()
        if p and p[0] in ("b", "d"):
            kind, t, first = p[0], float(p[1]) * 1e-9, True
        elif p and p[0] == "i" and kind == "b" and first:
            steps.append((t, root / p[1].replace("\\", "/")))
            first = False
    pick = [steps[i] for i in (1, 3, 6, 10, 15, 21)]
    fmt = FrameFormat(bits=12, black_level=14.7)
    sc = self_calibrate([read_frame(p, t, fmt=fmt) for t, p in pick])
    row = _row(sc)
    row["standard_K"] = EMVA_K
    row["relative_error_vs_K"] = round(sc.fit["g"] / EMVA_K - 1, 4)
    row["error_in_stated_stderr"] = round((sc.fit["g"] - EMVA_K) / sc.fit["g_stderr"], 2)
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="320x256", help="frame size WxH (default 320x256)")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--out", help="folder for the TIFF files (default: a temporary one)")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.out or tmp)
        folder.mkdir(parents=True, exist_ok=True)
        res = {"camera": {"gain_8bit": G8, "times": TIMES, "size": [w, h], "seed": args.seed}}
        res.update(brackets(folder, (h, w), args.seed))
    res["emva1288_ref001"] = emva()
    res["seconds"] = round(time.perf_counter() - t0, 1)
    json.dump(res, sys.stdout)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
