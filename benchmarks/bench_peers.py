"""Peers benchmark: hdrcap's merge against the HDR tools people use, on the same simulated DNGs.

Peers, each used the way its documentation intends:

* HDRMerge (``apt-get install hdrmerge``): ``hdrmerge --no-align --no-crop -b 32 -o out.dng in*.dng``
  (headless: ``QT_QPA_PLATFORM=offscreen``); its output DNG is read with rawpy.
* OpenCV ``MergeDebevec`` / ``MergeRobertson`` (``opencv-python-headless``) on 16-bit linear
  TIFFs (black subtracted, scaled to the white level, as ``dcraw -4 -D`` style converters write
  them; the mosaic replicated into 3 channels), with the exposure times, default linear response.
* colour-hdri ``image_stack_to_HDRI`` (default Debevec 1997 hat weighting, linear data, no CRF)
  on the same TIFFs as floats in [0, 1], with exposure time, f-number and ISO metadata.
* hdrcap: the installed ``hdrcap merge`` command (maximum-likelihood merge, default options,
  and with the probabilistic saturation model) with the matched dark frames and Table 2's
  parameters, with a calibration file holding the sensor's PRNU and dark-current maps (a full
  calibration) and one without them (nominal scalars, as a user without a flat-field
  calibration); its irradiance is read back from the EXR it writes.

Every tool runs in its own process (peers in their own venv, ``--setup`` creates it). The
timing columns compare the same work for every tool:

* ``whole_command_seconds`` (and ``..._per_megapixel``): the process's wall time from the input
  files to the output file, interpreter start, imports, reading and writing included;
* ``peak_rss_mb``: the process's maximum resident set (``os.wait4``);
* ``in_memory_merge_seconds`` (and ``..._per_megapixel``): the merge call alone on frames already
  in memory (a separate run for hdrcap, after a first call that compiles or loads the numba
  kernels, reported as ``first_call_seconds``); absent for HDRMerge, which has no such call.
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
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_command import hdrcap_exe, run_measured  # noqa: E402  (after the path set-up above)

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
import json, sys, time
sys.path.insert(0, sys.argv[2])
from hdrcap.pipeline.calibration import load_calibration
from hdrcap.pipeline.io.raw import read_frame
from hdrcap.pipeline.merge import accumulator as M
files, darks, calib, options = json.loads(sys.argv[1])
frames = [read_frame(f) for f in files]
dk = [read_frame(f) for f in darks]
cal = load_calibration(calib)
values, times, dvals = [f.data for f in frames], [f.exposure_time for f in frames], [d.data for d in dk]
crop = lambda a: None if a is None else a[:8, :8]
small = cal.replace(prnu=crop(cal.prnu), dark_current_map=crop(cal.dark_current_map))
t0 = time.perf_counter()
M.merge_arrays([crop(v) for v in values], times, small, darks=[crop(d) for d in dvals], **options)
first = time.perf_counter() - t0  # compiles the kernels or loads them from numba's cache
t0 = time.perf_counter()
res = M.merge_arrays(values, times, cal, darks=dvals, **options)
sec = time.perf_counter() - t0
print(json.dumps({"merge_seconds": sec, "first_call_seconds": first, "method": res.info.get("method")}))
"""


def setup_venv(venv: Path) -> None:
    """Create the peers' venv and install them (pip); install HDRMerge with apt-get when root."""
    if not (venv / "bin" / "python").exists():
        subprocess.check_call([sys.executable, "-m", "venv", str(venv)])
    subprocess.check_call(
        [str(venv / "bin" / "python"), "-m", "pip", "install", "-q", "opencv-python-headless", "colour-hdri"]
    )
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
    from hdrcap.pipeline.io.raw import read_frame

    times = []
    for i, f in enumerate(files):
        fr = read_frame(f)
        times.append(fr.exposure_time)
        lin = np.clip((fr.data.astype(np.float64) - spec.mu_R) / (spec.white_level - spec.mu_R), 0, 1)
        tif = work / f"frame_{i}.tif"
        tifffile.imwrite(tif, np.round(lin * 65535).astype(np.uint16))
        tiffs.append(str(tif))
    from hdrcap.pipeline.calibration import save_calibration
    from hdrcap.pipeline.params import Calibration

    maps = Calibration(
        p, prnu=cam.sensor.prnu.astype(np.float32), dark_current_map=cam.sensor.dark_current_map().astype(np.float32)
    )
    save_calibration(work / "calibration_maps.npz", maps, force=True)
    save_calibration(work / "calibration_nominal.npz", Calibration(p), force=True)
    return {
        "files": files,
        "darks": darks,
        "tiffs": tiffs,
        "times": times,
        "truth": scene,
        "spec": spec,
        "params": p,
        "sensor": cam.sensor,
    }


def scale_fit(y: np.ndarray, truth: np.ndarray, valid: np.ndarray) -> float:
    """Least-squares scale s minimising sum ((s y - X)/X)^2 over ``valid``."""
    r = y[valid] / truth[valid]
    r = r[np.isfinite(r)]
    return float(np.sum(r) / np.sum(r * r))


#: hdrcap's rows: calibration file, extra ``hdrcap merge`` options, whether the dark frames are
#: given, and the same options for the in-memory merge call.
HDRCAP_ROWS = {
    "hdrcap ML merge (PRNU + dark maps)": ("calibration_maps.npz", [], True, {}),
    "hdrcap ML merge (maps, probabilistic saturation)": (
        "calibration_maps.npz",
        ["--saturation", "probabilistic"],
        True,
        {"saturation": "probabilistic"},
    ),
    "hdrcap ML merge (maps, no dark frames: model darks)": (
        "calibration_maps.npz",
        [],
        False,
        {"dark_strategy": "model"},
    ),
    "hdrcap ML merge (nominal scalars)": ("calibration_nominal.npz", [], True, {}),
}


def run_hdrcap(name: str, sim: dict, work: Path) -> dict:
    """``hdrcap merge`` from the DNGs to an EXR (whole command; its irradiance saved as .npy for
    the accuracy columns), then the merge call alone in memory (a separate process)."""
    from hdrcap.pipeline.io.exr import read_exr

    calib, flags, with_darks, options = HDRCAP_ROWS[name]
    exr = work / f"hdrcap_{len(flags)}_{with_darks}_{calib}.exr"
    darks = ["--darks", *sim["darks"]] if with_darks else []
    r = run_measured(
        [
            hdrcap_exe(),
            "merge",
            *sim["files"],
            *darks,
            "--calibration",
            work / calib,
            *flags,
            "-o",
            exr,
            "--force",
            "--json",
        ]
    )
    r["whole_command_seconds"] = r["wall_seconds"]
    if r["returncode"] == 0:
        np.save(work / f"{exr.stem}.npy", read_exr(exr).channels["irradiance"].astype(np.float64))
        r["output"] = f"{exr.stem}.npy"
    mem = run_measured(
        [
            sys.executable,
            "-c",
            RUN_HDRCAP,
            json.dumps([sim["files"], sim["darks"], str(work / calib), options]),
            str(REPO),
        ]
    )
    if mem["returncode"] == 0 and mem["stdout"]:
        got = json.loads(mem["stdout"])
        r.update(
            in_memory_merge_seconds=got["merge_seconds"],
            first_call_seconds=got["first_call_seconds"],
            method=got.get("method"),
        )
    return r


def run_peer_script(script: str, sim: dict, work: Path, npy: str, kind: str, peers_py: str) -> dict:
    """A Python peer in its venv: whole process from the TIFFs to its .npy output, and the merge
    call's own time as the in-memory figure."""
    r = run_measured([peers_py, "-c", script, json.dumps([sim["tiffs"], sim["times"], str(work / npy), kind])])
    r["whole_command_seconds"] = r["wall_seconds"]
    if r["returncode"] == 0 and r["stdout"]:
        got = json.loads(r["stdout"])
        r.update(in_memory_merge_seconds=got["merge_seconds"], version=got.get("version"), output=npy)
    return r


def run_hdrmerge(sim: dict, work: Path, truth_shape) -> dict:
    """HDRMerge on the bright DNGs (whole command); its raw output, black subtracted, as .npy."""
    hdr_out = work / "hdrmerge.dng"
    if not shutil.which("hdrmerge"):
        return {"error": "hdrmerge not on PATH (apt-get install -y hdrmerge)"}
    hdr_out.unlink(missing_ok=True)
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen", XDG_RUNTIME_DIR=str(work))
    r = run_measured(["hdrmerge", "--no-align", "--no-crop", "-b", "32", "-o", hdr_out, *sim["files"]], env=env)
    r["whole_command_seconds"] = r["wall_seconds"]
    if r["returncode"] == 0 and hdr_out.exists():
        import rawpy

        with rawpy.imread(str(hdr_out)) as raw:
            data = raw.raw_image_visible.astype(np.float64)
            black = float(np.mean(raw.black_level_per_channel))
        if data.shape == truth_shape:
            np.save(work / "hdrmerge.npy", data - black)
            r["output"] = "hdrmerge.npy"
        else:
            r["error"] = f"output shape {data.shape} != input {truth_shape}"
    return r


PEER_SCRIPTS = {
    "OpenCV MergeDebevec (16-bit)": (RUN_OPENCV, "cv_debevec.npy", "debevec"),
    "OpenCV MergeRobertson (16-bit)": (RUN_OPENCV, "cv_robertson.npy", "robertson"),
    "colour-hdri image_stack_to_HDRI": (RUN_COLOUR, "colour_hdri.npy", ""),
}

#: Columns of the printed table; every timing column is the same work for every tool.
TABLE_COLUMNS = (
    "mean_snr_db",
    "min_snr_db",
    "lowest_decade_mean_snr_db",
    "mean_efficiency",
    "min_efficiency",
    "whole_command_seconds",
    "whole_command_seconds_per_megapixel",
    "peak_rss_mb",
    "in_memory_merge_seconds",
    "in_memory_merge_seconds_per_megapixel",
    "first_call_seconds",
    "scale_fit",
    "version",
    "method",
    "error",
    "nonfinite_pixels",
)


def accuracy(results: dict, sim: dict, work: Path, bins: int) -> dict:
    """SNR per irradiance bin of every output against the truth; adds the summary to each row."""
    from hdrcap.pipeline.evaluation import bound_variance, log_bins, snr_per_bin

    truth, sensor = sim["truth"], sim["sensor"]
    edges = log_bins(truth, bins)
    bound = bound_variance(
        truth, sim["times"], sim["params"], a=sensor.prnu, D=sensor.dark_current_map(), dark="matched"
    )
    valid = np.isfinite(bound)
    curves = {}
    for name, r in results.items():
        if r.get("returncode", 1) != 0 or not r.get("output"):
            r.setdefault("error", r.get("stderr", "failed"))
            continue
        y = np.load(work / r["output"])
        s = scale_fit(y, truth, valid & np.isfinite(y) & (y > 0))
        res = snr_per_bin(np.where(np.isfinite(y), s * y, 0.0), truth, edges, bound=bound, valid=valid)
        curves[name] = res
        snr = np.array([v for v in res["snr_db"] if v is not None])
        eff = np.array([v for v in res["efficiency"] if v is not None])
        lowest = [v for v in res["snr_db"][: max(1, bins // 4)] if v is not None]
        r.update(
            {
                "scale_fit": s,
                "mean_snr_db": float(snr.mean()),
                "min_snr_db": float(snr.min()),
                "lowest_decade_mean_snr_db": float(np.mean(lowest)),
                "mean_efficiency": float(eff.mean()),
                "min_efficiency": float(eff.min()),
                "nonfinite_pixels": int((~np.isfinite(y)).sum()),
            }
        )
    return curves


def table_rows(results: dict, mp: float) -> dict:
    """The printed columns of every row, with the per-megapixel timings."""
    table = {}
    for name, r in results.items():
        for key in ("whole_command_seconds", "in_memory_merge_seconds"):
            if r.get(key):
                r[f"{key}_per_megapixel"] = r[key] / mp
        table[name] = {k: r[k] for k in TABLE_COLUMNS if r.get(k) is not None}
    return table


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
    w, h = (int(v) for v in args.size.split("x"))
    work = args.out / "data"
    sim = simulate(work, args.camera, (h, w), args.seed)
    truth = sim["truth"]
    peers_py = str(args.venv / "bin" / "python")
    results: dict[str, dict] = {name: run_hdrcap(name, sim, work) for name in HDRCAP_ROWS}
    for name, (script, npy, kind) in PEER_SCRIPTS.items():
        if Path(peers_py).exists():
            results[name] = run_peer_script(script, sim, work, npy, kind, peers_py)
        else:
            results[name] = {"error": f"peers venv missing ({args.venv}); run with --setup"}
    results["HDRMerge"] = run_hdrmerge(sim, work, truth.shape)
    curves = accuracy(results, sim, work, args.bins)
    mp = truth.size / 1e6
    table = table_rows(results, mp)
    bound_snr = [v for v in next(iter(curves.values()))["bound_snr_db"] if v is not None] if curves else []
    out = {
        "camera": args.camera,
        "size": args.size,
        "megapixels": mp,
        "exposure_times": sim["times"],
        "irradiance_range": [float(truth.min()), float(truth.max())],
        "seed": args.seed,
        "bound_mean_snr_db": float(np.mean(bound_snr)) if bound_snr else None,
        "table": table,
        "curves": {
            k: {
                "center": v["center"],
                "snr_db": v["snr_db"],
                "efficiency": v["efficiency"],
                "bound_snr_db": v["bound_snr_db"],
            }
            for k, v in curves.items()
        },
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "peers.json").write_text(json.dumps(out, indent=1))
    if curves:
        plot(curves, args.out / "peers.png", f"{args.camera}, {args.size}, 6 exposures, 4 decades")
    print(json.dumps({"camera": args.camera, "size": args.size, "table": table}, indent=1))
    return 0


def plot(curves: dict, path: Path, title: str) -> None:
    from hdrcap.pipeline.plotting import new_figure, save_figure

    fig, ax = new_figure(figsize=(7.0, 4.2))
    first = next(iter(curves.values()))
    c = np.asarray(first["center"])
    ax.plot(
        c,
        np.array([np.nan if v is None else v for v in first["bound_snr_db"]], float),
        color="k",
        lw=2.4,
        alpha=0.3,
        label="bound 1/Σw",
    )
    for name, r in curves.items():
        ax.plot(c, np.array([np.nan if v is None else v for v in r["snr_db"]], float), lw=1.2, label=name)
    ax.set_xscale("log")
    ax.set_xlabel("irradiance X (e⁻/s)")
    ax.set_ylabel("SNR (dB), after a global scale fit")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    save_figure(fig, path, force=True, dpi=72)


if __name__ == "__main__":
    sys.exit(main())
