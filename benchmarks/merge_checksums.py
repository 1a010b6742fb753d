"""Checksums of the optimal merge's outputs over its code paths; prints one JSON object.

Run before and after a change of the merge kernel (same machine: the compiled code depends on
the CPU's vector width and FMA) and compare: every checksum must be equal, i.e. the change is
bit-identical. Paths covered: matched dark frames (three-frame and single-frame loops),
float32 and float64 weights, the model strategy with PRNU, bias and dark-current maps, one
master dark with a reference time, per-exposure master darks, mixed strategies, the
probabilistic saturation model, float input frames, and the streaming first pass.

Usage: python benchmarks/merge_checksums.py [--out FILE] [--compare FILE]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys

import numpy as np

TIMES = [0.001, 0.004, 0.016, 0.064, 0.25, 1.0, 0.5]


def _digest(res) -> str:
    h = hashlib.sha256()
    for a in (res.irradiance, res.sigma, res.nexp):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(
        repr(
            (
                res.info["iterations_used_mean"],
                res.info["iterations_used_max"],
                res.info["saturated_everywhere"],
                res.info["weights_precision"],
            )
        ).encode()
    )
    return h.hexdigest()[:16]


def checksums() -> dict[str, str]:
    from hdrcap.api import simulate
    from hdrcap.pipeline.merge import accumulator as pm
    from hdrcap.pipeline.params import Calibration

    sim = simulate("camera-A", "hdr", TIMES, seed=3, shape=(70, 132), darks=True)
    frames, darks, cal = list(sim.frames), list(sim.darks), sim.calibration
    scalar = Calibration(cal.params)
    out: dict[str, str] = {}

    def run(name, *args, **kw):
        out[name] = _digest(pm.merge_arrays(*args, **kw))

    run("matched", frames, TIMES, cal, darks)
    run("matched_6", frames[:6], TIMES[:6], cal, darks[:6])
    run("matched_4_scalar", frames[:4], TIMES[:4], scalar, darks[:4], prnu="scalar")
    run("model_maps", frames, TIMES, cal)
    run("model_scalar", frames, TIMES, scalar)
    run(
        "master_one",
        frames,
        TIMES,
        cal,
        np.mean(darks[:3], axis=0).astype(np.float32),
        n_dark=3,
        master_dark_time=0.004,
    )
    run("master_per_exposure", frames, TIMES, cal, darks, dark_strategy="master", n_dark=4)
    run(
        "mixed",
        frames,
        TIMES,
        cal,
        [d if i % 3 else None for i, d in enumerate(darks)],
        dark_strategies=["model" if i % 3 == 0 else ("master" if i % 3 == 1 else "matched") for i in range(len(TIMES))],
        n_darks=[None, 5, None] * 2 + [None],
    )
    run("probabilistic", frames, TIMES, cal, darks, saturation="probabilistic")
    run("no_rule", frames, TIMES, cal, darks, saturation_sigmas=0.0, iterations=5, tolerance=0.0)
    run("float_frames", [f.astype(np.float32) for f in frames], TIMES, cal, darks)
    old = pm.SINGLE_PRECISION_WEIGHTS
    pm.SINGLE_PRECISION_WEIGHTS = False
    try:
        run("matched_float64", frames, TIMES, cal, darks)
        run("model_float64", frames, TIMES, cal)
    finally:
        pm.SINGLE_PRECISION_WEIGHTS = old
    acc = pm.MergeAccumulator(cal, frames[0].shape)
    for f, t, d in zip(frames, TIMES, darks):
        acc.add(f, t, d)
    out["streamed_matched"] = _digest(acc.result())
    acc = pm.MergeAccumulator(cal, frames[0].shape, master_dark=darks[2], master_dark_time=0.016)
    for f, t in zip(frames, TIMES):
        acc.add(f, t)
    out["streamed_master"] = _digest(acc.result())
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", help="also write the checksums to this JSON file")
    ap.add_argument("--compare", help="JSON file of earlier checksums: exit 1 unless all are equal")
    args = ap.parse_args(argv)
    sums = checksums()
    print(json.dumps(sums, indent=1))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(sums, f, indent=1)
    if args.compare:
        with open(args.compare) as f:
            before = json.load(f)
        diff = sorted(k for k in set(before) | set(sums) if before.get(k) != sums.get(k))
        print(json.dumps({"identical": not diff, "differ": diff}))
        return 1 if diff else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
