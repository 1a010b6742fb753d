"""Peers benchmark: hdrcap's merge against the HDR tools people use, on the same simulated DNGs.

Peers, each used the way its documentation intends:

* HDRMerge (``apt-get install hdrmerge``): ``hdrmerge --no-align --no-crop -b 32 -o out.dng in*.dng``
  (headless: ``QT_QPA_PLATFORM=offscreen``); its output DNG is read with rawpy.
* OpenCV ``MergeDebevec`` / ``MergeRobertson`` (``opencv-python-headless``) on 16-bit linear
  TIFFs (black subtracted, scaled to the white level, as ``dcraw -4 -D`` style converters write
  them; the mosaic replicated into 3 channels), with the exposure times, default linear response.
* colour-hdri ``image_stack_to_HDRI`` (default Debevec 1997 hat weighting, linear data, no CRF)
  on the same TIFFs as floats in [0, 1], with exposure time, f-number and ISO metadata.
* hdrcap: the maximum-likelihood merge (``pipeline.merge``, default options, and with the
  probabilistic saturation model) with the matched dark frames and Table 2's parameters, with
  the sensor's PRNU and dark-current maps (a full calibration) and without them (nominal
  scalars, as a user without a flat-field calibration). Its time excludes the first call
  (numba compilation or cache load, reported as ``first_call_seconds``).

Every tool runs in its own process (peers in their own venv, ``--setup`` creates it); the merge
time is measured inside the process around the merge call only (reading excluded) and the peak
memory is the process's maximum resident set (``os.wait4``), interpreter and imports included.
Accuracy: SNR per irradiance bin against the simulator's truth after a global least-squares
scale fit of the relative error (the peers do not know the gain), and the Cramér-Rao bound.

Usage::

    python benchmarks/bench_peers.py --setup            # venv benchmarks/_work/venv + peers
    python benchmarks/bench_peers.py [--size 768x512] [--camera camera-B] [--seed 0]

Prints one JSON table on stdout and writes ``peers.json`` and ``peers.png`` into ``--out``
(default ``benchmarks/_work/peers``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

WORK = REPO / "benchmarks" / "_work"
DEFAULT_VENV = WORK / "venv"
TIMES = (1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4, 1.0)  # two stops apart, as the paper's six

RUN_OPENCV = r"""
import json, sys, time, numpy as np, cv2
files, times, out, kind = json.loads(sys.argv[1])
imgs = [cv2.imread(f, cv2.IMREAD_UNCHANGED) for f in files]
imgs = [np.ascontiguousarray(np.repeat(i[:, :, None], 3, axis=2)) for i in imgs]
t0 = time.perf_counter()
merger = cv2.createMergeDebevec() if kind == "debevec" else cv2.createMergeRobertson()
hdr = merger.process(imgs, times=np.asarray(times, np.float32))
sec = time.perf_counter() - t0
np.save(out, hdr[:, :, 0].astype(np.float64))
print(json.dumps({"merge_seconds": sec, "version": cv2.__version__}))
"""

RUN_COLOUR = r"""
import json, sys, time, warnings, numpy as np, cv2
warnings.filterwarnings("ignore")
import colour_hdri
from colour_hdri import Image, ImageStack, Metadata, image_stack_to_HDRI
files, times, out, kind = json.loads(sys.argv[1])
stack = ImageStack()
for f, t in sorted(zip(files, times), key=lambda ft: ft[1]):  # shortest exposure first, as from_files sorts
    data = cv2.imread(f, cv2.IMREAD_UNCHANGED).astype(np.float64) / 65535.0
    stack.append(Image(f, data, Metadata(f_number=8.0, exposure_time=t, iso=400)))
t0 = time.perf_counter()
hdr = image_stack_to_HDRI(stack)
sec = time.perf_counter() - t0
np.save(out, np.asarray(hdr, np.float64))
print(json.dumps({"merge_seconds": sec, "version": colour_hdri.__version__}))
"""

RUN_HDRCAP = r"""
import json, sys, time, numpy as np
sys.path.insert(0, sys.argv[2])
from hdrcap.pipeline.io import read_frame
from hdrcap.pipeline.params import Calibration, SensorParams
from hdrcap.pipeline import merge as M
files, darks, out, calib, options = json.loads(sys.argv[1])
frames = [read_frame(f) for f in files]
dk = [read_frame(f) for f in darks]
cal = Calibration(SensorParams(**calib["params"]),
                  prnu=np.load(calib["prnu"]) if calib.get("prnu") else None,
                  dark_current_map=np.load(calib["dcm"]) if calib.get("dcm") else None)
values, times, dvals = [f.data for f in frames], [f.exposure_time for f in frames], [d.data for d in dk]
crop = lambda a: None if a is None else a[:8, :8]
small = cal.replace(prnu=crop(cal.prnu), dark_current_map=crop(cal.dark_current_map))
t0 = time.perf_counter()
M.merge_arrays([crop(v) for v in values], times, small, darks=[crop(d) for d in dvals], **options)
first = time.perf_counter() - t0  # compiles the kernels or loads them from numba's cache
t0 = time.perf_counter()
res = M.merge_arrays(values, times, cal, darks=dvals, **options)
sec = time.perf_counter() - t0
np.save(out, res.irradiance.astype(np.float64))
print(json.dumps({"merge_seconds": sec, "first_call_seconds": first, "method": res.info.get("method")}))
"""


def run_measured(cmd, env=None, cwd=None) -> dict:
    """Run ``cmd``; return wall time, peak RSS (MB, os.wait4), return code, stdout/stderr tails."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=cwd, text=True)
    out, err = "", ""
    # drain pipes, then reap with wait4 for the child's own rusage
    out, err = proc.stdout.read(), proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    return {"returncode": proc.returncode, "wall_seconds": wall, "peak_rss_mb": usage.ru_maxrss / 1024.0,
            "stdout": out.strip().splitlines()[-1] if out.strip() else "", "stderr": err.strip()[-400:]}


def setup_venv(venv: Path) -> None:
    """Create the peers' venv and install them (pip); install HDRMerge with apt-get when root."""
    if not (venv / "bin" / "python").exists():
        subprocess.check_call([sys.executable, "-m", "venv", str(venv)])
    subprocess.check_call([str(venv / "bin" / "python"), "-m", "pip", "install", "-q", "opencv-python-headless",
                           "colour-hdri"])
    if shutil.which("hdrmerge") is None:
        if os.geteuid() == 0:
            subprocess.call(["apt-get", "install", "-y", "hdrmerge"])
        else:
            print("HDRMerge is missing: run `sudo apt-get install -y hdrmerge`", file=sys.stderr)


def simulate(work: Path, camera: str, shape, seed: int):
    """Write the DNG bracket + darks and 16-bit linear TIFFs; return paths, truth and sensor."""
    import tifffile

    from hdrcap.mock_camera import PRESETS
    from hdrcap.mock_camera.backend import SimulatedCamera
    from hdrcap.mock_camera.scenes import make_scene

    spec = PRESETS[camera]
    p = spec.nominal_params()  # Table 2 values, as a user's calibration gives them
    x_max = 0.8 * (p.v_sat - p.mu_R) / (p.g * TIMES[0])
    scene = make_scene("gradient", shape, decades=4.0, x_max=x_max)
    cam = SimulatedCamera(spec, scene, seed=seed)
    work.mkdir(parents=True, exist_ok=True)
    files, darks, tiffs = [], [], []
    for i, t in enumerate(TIMES):
        f = cam.capture_to(work / f"frame_{i}.dng", t, overwrite=True)
        d = cam.capture_to(work / f"dark_{i}.dng", t, dark=True, overwrite=True)
        files.append(str(f))
        darks.append(str(d))
    from hdrcap.pipeline.io import read_frame

    times = []
    for i, f in enumerate(files):
        fr = read_frame(f)
        times.append(fr.exposure_time)
        lin = np.clip((fr.data.astype(np.float64) - spec.mu_R) / (spec.white_level - spec.mu_R), 0, 1)
        tif = work / f"frame_{i}.tif"
        tifffile.imwrite(tif, np.round(lin * 65535).astype(np.uint16))
        tiffs.append(str(tif))
    np.save(work / "prnu.npy", cam.sensor.prnu.astype(np.float32))
    np.save(work / "dcm.npy", cam.sensor.dark_current_map().astype(np.float32))
    return {"files": files, "darks": darks, "tiffs": tiffs, "times": times, "truth": scene, "spec": spec,
            "params": p, "sensor": cam.sensor}


def scale_fit(y: np.ndarray, truth: np.ndarray, valid: np.ndarray) -> float:
    """Least-squares scale s minimising sum ((s y - X)/X)^2 over ``valid``."""
    r = y[valid] / truth[valid]
    r = r[np.isfinite(r)]
    return float(np.sum(r) / np.sum(r * r))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--setup", action="store_true", help="create the peers' venv and install the peers, then exit")
    ap.add_argument("--venv", type=Path, default=Path(os.environ.get("HDRCAP_PEERS_VENV", DEFAULT_VENV)))
    ap.add_argument("--camera", default="camera-B")
    ap.add_argument("--size", default="768x512", help="WIDTHxHEIGHT of the mosaic")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--bins", type=int, default=24)
    ap.add_argument("--out", type=Path, default=WORK / "peers")
    args = ap.parse_args(argv)
    if args.setup:
        setup_venv(args.venv)
        return 0
    from hdrcap.pipeline.evaluation import bound_variance, log_bins, snr_per_bin

    w, h = (int(v) for v in args.size.split("x"))
    work = args.out / "data"
    sim = simulate(work, args.camera, (h, w), args.seed)
    truth, p = sim["truth"], sim["params"]
    peers_py = str(args.venv / "bin" / "python")
    results: dict[str, dict] = {}

    def calib_json(maps: bool):
        return {"params": p.to_dict(), "prnu": str(work / "prnu.npy") if maps else None,
                "dcm": str(work / "dcm.npy") if maps else None}

    def hdrcap(npy, maps, options):
        return [sys.executable, "-c", RUN_HDRCAP,
                json.dumps([sim["files"], sim["darks"], str(work / npy), calib_json(maps), options]), str(REPO)]

    runs = {
        "hdrcap ML merge (PRNU + dark maps)": hdrcap("hdrcap_maps.npy", True, {}),
        "hdrcap ML merge (maps, probabilistic saturation)": hdrcap("hdrcap_prob.npy", True,
                                                                   {"saturation": "probabilistic"}),
        "hdrcap ML merge (maps, no dark frames: model darks)": hdrcap("hdrcap_model.npy", True,
                                                                      {"dark_strategy": "model"}),
        "hdrcap ML merge (nominal scalars)": hdrcap("hdrcap_nominal.npy", False, {}),
        "OpenCV MergeDebevec (16-bit)": [peers_py, "-c", RUN_OPENCV,
                                         json.dumps([sim["tiffs"], sim["times"], str(work / "cv_debevec.npy"),
                                                     "debevec"])],
        "OpenCV MergeRobertson (16-bit)": [peers_py, "-c", RUN_OPENCV,
                                           json.dumps([sim["tiffs"], sim["times"], str(work / "cv_robertson.npy"),
                                                       "robertson"])],
        "colour-hdri image_stack_to_HDRI": [peers_py, "-c", RUN_COLOUR,
                                            json.dumps([sim["tiffs"], sim["times"], str(work / "colour_hdri.npy"),
                                                        ""])],
    }
    outputs = {"hdrcap ML merge (PRNU + dark maps)": "hdrcap_maps.npy",
               "hdrcap ML merge (maps, probabilistic saturation)": "hdrcap_prob.npy",
               "hdrcap ML merge (maps, no dark frames: model darks)": "hdrcap_model.npy",
               "hdrcap ML merge (nominal scalars)":
               "hdrcap_nominal.npy", "OpenCV MergeDebevec (16-bit)": "cv_debevec.npy",
               "OpenCV MergeRobertson (16-bit)": "cv_robertson.npy", "colour-hdri image_stack_to_HDRI": "colour_hdri.npy"}
    for name, cmd in runs.items():
        if cmd[0] == peers_py and not Path(peers_py).exists():
            results[name] = {"error": f"peers venv missing ({args.venv}); run with --setup"}
            continue
        r = run_measured(cmd)
        results[name] = r
        if r["returncode"] == 0 and r["stdout"]:
            r.update(json.loads(r["stdout"]))
    # HDRMerge: a command-line tool on the DNGs
    hdr_out = work / "hdrmerge.dng"
    if shutil.which("hdrmerge"):
        if hdr_out.exists():
            hdr_out.unlink()
        env = dict(os.environ, QT_QPA_PLATFORM="offscreen", XDG_RUNTIME_DIR=str(work))
        r = run_measured(["hdrmerge", "--no-align", "--no-crop", "-b", "32", "-o", str(hdr_out), *sim["files"]],
                         env=env)
        r["merge_seconds"] = r["wall_seconds"]  # includes reading the DNGs and writing the output
        results["HDRMerge"] = r
        if r["returncode"] == 0 and hdr_out.exists():
            import rawpy

            with rawpy.imread(str(hdr_out)) as raw:
                data = raw.raw_image_visible.astype(np.float64)
                black = float(np.mean(raw.black_level_per_channel))
            if data.shape == truth.shape:
                np.save(work / "hdrmerge.npy", data - black)
                outputs["HDRMerge"] = "hdrmerge.npy"
            else:
                r["error"] = f"output shape {data.shape} != input {truth.shape}"
    else:
        results["HDRMerge"] = {"error": "hdrmerge not on PATH (apt-get install -y hdrmerge)"}

    edges = log_bins(truth, args.bins)
    sensor = sim["sensor"]
    bound = bound_variance(truth, sim["times"], p, a=sensor.prnu, D=sensor.dark_current_map(), dark="matched")
    valid = np.isfinite(bound)
    curves = {}
    for name, fname in outputs.items():
        r = results[name]
        if r.get("returncode", 1) != 0 or not (work / fname).exists():
            r.setdefault("error", r.get("stderr", "failed"))
            continue
        y = np.load(work / fname)
        fit_ok = valid & np.isfinite(y) & (y > 0)
        s = scale_fit(y, truth, fit_ok)
        est = np.where(np.isfinite(y), s * y, 0.0)
        res = snr_per_bin(est, truth, edges, bound=bound, valid=valid)
        curves[name] = res
        snr = np.array([v for v in res["snr_db"] if v is not None])
        eff = np.array([v for v in res["efficiency"] if v is not None])
        lowest = [v for v in res["snr_db"][: max(1, args.bins // 4)] if v is not None]
        r.update({"scale_fit": s, "mean_snr_db": float(snr.mean()), "min_snr_db": float(snr.min()),
                  "lowest_decade_mean_snr_db": float(np.mean(lowest)), "mean_efficiency": float(eff.mean()),
                  "min_efficiency": float(eff.min()), "nonfinite_pixels": int((~np.isfinite(y)).sum())})
    mp = truth.size / 1e6
    table = {}
    for name, r in results.items():
        row = {k: r.get(k) for k in ("mean_snr_db", "min_snr_db", "lowest_decade_mean_snr_db", "mean_efficiency",
                                     "min_efficiency", "merge_seconds", "wall_seconds", "peak_rss_mb",
                                     "scale_fit", "version", "method", "error", "nonfinite_pixels",
                                     "first_call_seconds")
               if r.get(k) is not None}
        if r.get("merge_seconds"):
            row["merge_seconds_per_megapixel"] = r["merge_seconds"] / mp
        table[name] = row
    bound_snr = [v for v in next(iter(curves.values()))["bound_snr_db"] if v is not None] if curves else []
    out = {"camera": args.camera, "size": args.size, "megapixels": mp, "exposure_times": sim["times"],
           "irradiance_range": [float(truth.min()), float(truth.max())], "seed": args.seed,
           "bound_mean_snr_db": float(np.mean(bound_snr)) if bound_snr else None, "table": table,
           "curves": {k: {"center": v["center"], "snr_db": v["snr_db"], "efficiency": v["efficiency"],
                          "bound_snr_db": v["bound_snr_db"]} for k, v in curves.items()}}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "peers.json").write_text(json.dumps(out, indent=1))
    if curves:
        plot(curves, args.out / "peers.png", f"{args.camera}, {args.size}, 6 exposures, 4 decades")
    print(json.dumps({"camera": args.camera, "size": args.size, "table": table}, indent=1))
    return 0


def plot(curves: dict, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.0, 4.2))
    first = next(iter(curves.values()))
    c = np.asarray(first["center"])
    ax.plot(c, np.array([np.nan if v is None else v for v in first["bound_snr_db"]], float), color="k", lw=2.4,
            alpha=0.3, label="bound 1/Σw")
    for name, r in curves.items():
        ax.plot(c, np.array([np.nan if v is None else v for v in r["snr_db"]], float), lw=1.2, label=name)
    ax.set_xscale("log")
    ax.set_xlabel("irradiance X (e⁻/s)")
    ax.set_ylabel("SNR (dB), after a global scale fit")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=72)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
