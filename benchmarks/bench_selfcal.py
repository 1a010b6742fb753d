"""Merging without a calibration: ``hdrcap merge *.dng -o out.exr`` (self-calibrated from the
bracket) against HDRMerge on the same DNG files.

The bracket: a simulated 14-bit sensor (g = 0.4 DN/e-, black 512 DN, sigma_R^2 = 9 DN^2, 1 %
PRNU, 0.5 e-/s dark current, ADC clipping before the full well), 5 exposures 1/2000 s to 2 s
(3 EV apart), no dark frames, an HDR scene of 6 decades. Both tools get only the DNG files.

Figures (JSON on stdout, also ``selfcal.json`` in ``--out``):

* per irradiance decade of the truth: SNR (dB) = 10 log10(mean X^2 / mean (s y - X)^2) of each
  tool's output y after its own global scale fit s (:func:`scale_fit`; HDRMerge does not know
  the gain), and hdrcap's without any fit;
* hdrcap's estimated gain and read-noise variance against the simulator's, with their standard
  errors, and the spread (standard deviation) of z = (y - a X) / sigma per decade, a X being
  the irradiance each photosite receives (PRNU a included: a bracket cannot separate it from
  the scene).

Usage::

    python benchmarks/bench_selfcal.py [--size 1024x768] [--seed 0] [--out DIR]

HDRMerge is installed with apt-get when missing (root), run headless with
``QT_QPA_PLATFORM=offscreen``; its float DNG is read with tifffile, which needs ``imagecodecs``
for HDRMerge's compression (``pip install imagecodecs``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_command import ensure_hdrmerge, hdrcap_exe, run_measured  # noqa: E402
from bench_peers import run_hdrmerge  # noqa: E402

#: The bracket: 1/2000 s to 2 s, 5 exposures (nominal shutter speeds, about 3 EV apart).
TIMES = (1 / 2000, 1 / 250, 1 / 30, 1 / 4, 2.0)
GAIN = 0.4


def sensor_spec():
    """The simulated 14-bit sensor (ADC clips before the full well)."""
    from hdrcap.mock_camera.sensor import SensorSpec

    return SensorSpec(
        name="sim-14bit",
        g=GAIN,
        mu_R=512.0,
        sigma2_R=9.0,
        bits=14,
        full_well=1.1 * (16383 - 512) / GAIN,
        iso=200,
        model="Simulated 14-bit",
    )


def simulate(work: Path, shape, seed: int) -> dict:
    """Write the DNG bracket; return the files, the truth and the sensor."""
    from hdrcap.mock_camera.backend import SimulatedCamera
    from hdrcap.mock_camera.scenes import make_scene

    spec = sensor_spec()
    x_max = 0.8 * (spec.white_level - spec.mu_R) / (spec.g * TIMES[0])
    scene = make_scene("hdr", shape, decades=6.0, x_max=x_max)
    cam = SimulatedCamera(spec, scene, seed=seed)
    work.mkdir(parents=True, exist_ok=True)
    files = [str(cam.capture_to(work / f"frame_{i}.dng", t, overwrite=True)) for i, t in enumerate(TIMES)]
    return {"files": files, "truth": scene, "sensor": cam.sensor, "spec": spec}


def scale_fit(y: np.ndarray, truth: np.ndarray, valid: np.ndarray) -> float:
    """The global scale s that maps ``y`` onto the truth: the median of X / y over ``valid``
    (robust: a least-squares fit of the relative error is pulled by a few gross errors)."""
    ok = valid & np.isfinite(y) & (y > 0)
    return float(np.median(truth[ok] / y[ok]))


def per_decade(y: np.ndarray, truth: np.ndarray, valid: np.ndarray) -> dict:
    """SNR (dB) per decade of the truth: 10 log10(mean X^2 / mean (y - X)^2)."""
    out = {}
    lo = np.floor(np.log10(truth[valid].min()))
    hi = np.ceil(np.log10(truth[valid].max()))
    for e in np.arange(lo, hi):
        s = valid & (truth >= 10**e) & (truth < 10 ** (e + 1))
        if s.sum() >= 100:
            out[f"1e{int(e)}"] = float(10 * np.log10(np.mean(truth[s] ** 2) / np.mean((y[s] - truth[s]) ** 2)))
    return out


def z_spread(img, received: np.ndarray, truth: np.ndarray) -> dict:
    """Standard deviation of z = (y - a X) / sigma per decade of the truth."""
    ch = img.channels
    ok = ch["nexp"] > 0
    z = (ch["irradiance"] - received) / np.where(ok, ch["sigma"], 1.0)
    out = {}
    for e in np.arange(np.floor(np.log10(truth.min())), np.ceil(np.log10(truth.max()))):
        s = ok & (truth >= 10**e) & (truth < 10 ** (e + 1))
        if s.sum() >= 100:
            out[f"1e{int(e)}"] = float(np.std(z[s]))
    return out


def read_hdrmerge(path: Path) -> np.ndarray:
    """HDRMerge's float CFA data, black subtracted, DN (LibRaw's ``raw_image_visible`` would
    give it rounded to integers below the white level, losing the low decades). Its tiles
    use the DNG floating-point predictor: tifffile needs ``imagecodecs`` (``pip install
    imagecodecs``)."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        raw = next(p for p in tif.pages[0].pages if p.photometric == 32803)
        black = np.mean(raw.tags[50714].value) if 50714 in raw.tags else 0.0
        return raw.asarray().astype(np.float64) - black


def main(argv=None) -> int:
    from hdrcap.mock_camera.scenes import parse_size
    from hdrcap.pipeline.io.exr import read_exr

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="1024x768", help="WIDTHxHEIGHT of the mosaic")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "_work" / "selfcal")
    args = ap.parse_args(argv)
    work = args.out
    sim = simulate(work, parse_size(args.size), args.seed)
    truth = sim["truth"]
    exr = work / "hdrcap.exr"
    r = run_measured([hdrcap_exe(), "merge", *sim["files"], "-o", exr, "--force", "--json"])
    if r["returncode"] != 0:
        print(json.dumps({"error": r["stderr"]}))
        return 1
    img = read_exr(exr)
    y = img.channels["irradiance"].astype(np.float64)
    valid = img.channels["nexp"] > 0
    sc = img.header["self_calibration"]
    results = {"hdrcap (no calibration)": {"seconds": r["wall_seconds"], "snr_db_per_decade": {}}}
    s = scale_fit(y, truth, valid & (y > 0))
    results["hdrcap (no calibration)"].update(
        scale_fit=s,
        snr_db_per_decade=per_decade(s * y, truth, valid),
        snr_db_per_decade_no_fit=per_decade(y, truth, valid),
        z_spread_per_decade=z_spread(img, sim["sensor"].prnu * truth, truth),
        gain={
            "estimated": sc["gain"]["value"],
            "stderr": sc["gain"]["stderr"],
            "true": sim["spec"].g,
            "relative_error": sc["gain"]["value"] / sim["spec"].g - 1,
        },
        read_noise_variance={
            "estimated": sc["read_noise_variance"]["value"],
            "stderr": sc["read_noise_variance"]["stderr"],
            "true": sim["spec"].sigma2_R,
        },
    )
    if ensure_hdrmerge():
        h = run_hdrmerge({"files": sim["files"]}, work, truth.shape)
        if h.get("output"):
            yh = read_hdrmerge(work / "hdrmerge.dng")
            ok = np.isfinite(yh) & (yh > 0)
            sh = scale_fit(yh, truth, ok)
            results["HDRMerge"] = {
                "seconds": h["wall_seconds"],
                "scale_fit": sh,
                "snr_db_per_decade": per_decade(sh * yh, truth, np.isfinite(yh)),
            }
        else:
            results["HDRMerge"] = {"error": h.get("error") or h.get("stderr")}
    mine = results["hdrcap (no calibration)"]["snr_db_per_decade"]
    peer = results.get("HDRMerge", {}).get("snr_db_per_decade", {})
    results["hdrcap_minus_hdrmerge_db"] = {k: mine[k] - peer[k] for k in mine if k in peer}
    (work / "selfcal.json").write_text(json.dumps(results, indent=2))
    print(json.dumps(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
