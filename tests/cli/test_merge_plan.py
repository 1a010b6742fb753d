"""``hdrcap merge --plan`` and the calibration's dark library: per-exposure dark strategies,
the planner's merge options (the command line wins), the ``planner`` EXR header, one-line
errors. Accuracy is judged against the simulator's truth."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from hdrcap.cli import main
from hdrcap.pipeline.io.exr import read_exr
from hdrcap.pipeline.io.raw import read_frame

TIMES = [0.001, 0.004, 0.016, 0.064, 0.25, 1.0]
MIXED = ["matched", "model", "matched", "model", "matched", "model"]
N_LIB = 8


def _run(capsys, *args):
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def _z(img, truth):
    irr, sig, nexp = (img.channels[k].astype(np.float64) for k in ("irradiance", "sigma", "nexp"))
    ok = nexp > 0
    return (irr[ok] - truth[ok]) / sig[ok]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A camera-B bracket with one dark frame per time, and a calibration that knows the
    sensor's fixed patterns (PRNU, dark-current map) with a dark library of N_LIB-frame
    master darks for all times but 0.25 s."""
    from hdrcap.mock_camera import PRESETS
    from hdrcap.mock_camera.sensor import SimulatedSensor
    from hdrcap.pipeline.calibration import save_calibration
    from hdrcap.pipeline.calibration.darklibrary import DarkLibrary
    from hdrcap.pipeline.params import Calibration

    root = tmp_path_factory.mktemp("mergeplan")
    sim = root / "sim"
    assert (
        main(
            [
                "simulate",
                "--camera",
                "camera-B",
                "--out",
                str(sim),
                "--size",
                "64x48",
                "--darks",
                "--seed",
                "5",
                "--decades",
                "3",
                "--x-max",
                "2e4",
                "--json",
            ]
        )
        == 0
    )
    frames = sorted(sim.glob("frame_*.dng"))
    darks = sorted(sim.glob("dark_*.dng"))
    sensor = SimulatedSensor(PRESETS["camera-B"], (48, 64), seed=5)  # same fixed patterns as the simulation
    lib = DarkLibrary(root / "darklib")
    rng = np.random.default_rng([5, 99])  # noise independent of the bracket's
    model = read_frame(frames[0]).camera
    for t in TIMES:
        if t != 0.25:
            stack = [sensor.expose(0.0, t, dark=True, rng=rng) for _ in range(N_LIB)]
            lib.add(np.mean(stack, axis=0), N_LIB, camera=model, iso=None, exposure_time=t)
    cal = Calibration(
        params=PRESETS["camera-B"].nominal_params(),
        prnu=sensor.prnu.astype(np.float32),
        dark_current_map=sensor.dark_current_map().astype(np.float32),
        provenance={"source": "simulator truth"},
        dark_library=str(root / "darklib"),
    )
    save_calibration(root / "cal.npz", cal)
    truth = read_exr(sim / "truth.exr").channels["irradiance"].astype(np.float64)
    return {"root": root, "frames": frames, "darks": darks, "cal": root / "cal.npz", "truth": truth}


def _plan(path, darks=MIXED, times=TIMES, **more):
    plan = {
        "exposures": list(times),
        "darks": list(darks),
        "predicted_min_snr_db": 21.5,
        "total_time_s": 2.9,
        "decisions": {
            "saturation": {"choice": "probabilistic", "reason": "test", "figure": 0.3},
            "prnu": {"choice": "map", "reason": "test", "figure": 0.5},
            "iterations": {"choice": 6, "reason": "test", "figure": 0.01},
        },
        **more,
    }
    path.write_text(json.dumps(plan))
    return path


def test_merge_plan_applies_per_exposure_strategies_and_records_decisions(data, tmp_path, capsys):
    plan = _plan(tmp_path / "plan.json")  # no merge_options key: derived from the decisions
    out = tmp_path / "m.exr"
    code, _, err = _run(
        capsys,
        "merge",
        *data["frames"],
        "--darks",
        *data["darks"],
        "--calibration",
        data["cal"],
        "--plan",
        plan,
        "--iterations",
        "9",
        "-o",
        out,
        "--json",
    )
    assert code == 0, err
    img = read_exr(out)
    m, p = img.header["merge"], img.header["planner"]
    assert m["dark_strategies"] == MIXED and m["dark_strategy"] == "mixed"
    assert m["iterations"] == 9 and m["saturation"] == "probabilistic" and m["prnu"] == "map"
    assert p["options_from_plan"] == {"saturation": "probabilistic", "prnu": "map", "saturation_sigmas": 3.0}
    assert p["options_overridden"] == {"iterations": {"plan": 6, "used": 9}}
    assert p["decisions"]["iterations"]["choice"] == 6 and p["predicted_min_snr_db"] == 21.5
    assert p["plan_sha256"] == hashlib.sha256(plan.read_bytes()).hexdigest() and p["plan_file"] == str(plan)
    src = img.header["dark_sources"]
    assert [s == "model" for s in src] == [s == "model" for s in MIXED]
    assert all(f"_{t:g}s" in s for t, s in zip(TIMES, src) if s != "model")
    z = _z(img, data["truth"])
    assert 0.9 < z.std() < 1.1 and abs(z.mean()) < 0.1, (z.std(), z.mean())
    # The model frames carry no dark-frame noise: in the darkest tenth of the scene the 1 s frame
    # (model) dominates with ~20 e-, and its variance g^2 tX + s_R^2 ~ 35 DN^2 is well below the
    # matched frame's g^2 tX + 2 s_R^2 ~ 53 DN^2 (Eq. 3, 5): sigma about 0.8x the all-matched merge's.
    code, _, err = _run(
        capsys,
        "merge",
        *data["frames"],
        "--darks",
        *data["darks"],
        "--calibration",
        data["cal"],
        "--dark-strategy",
        "matched",
        "--saturation",
        "probabilistic",
        "-o",
        tmp_path / "all.exr",
    )
    assert code == 0, err
    ref = read_exr(tmp_path / "all.exr").channels["sigma"]
    dark = data["truth"] < np.quantile(data["truth"], 0.1)
    assert np.median(img.channels["sigma"][dark] / ref[dark]) < 0.9


def test_master_darks_from_the_calibration_dark_library(data, tmp_path, capsys):
    five = [f for f in data["frames"] if "0.25" not in f.name]
    out = tmp_path / "lib.exr"
    code, _, err = _run(capsys, "merge", *five, "--calibration", data["cal"], "--dark-strategy", "master", "-o", out)
    assert code == 0, err
    img = read_exr(out)
    assert img.header["merge"]["n_dark_per_frame"] == [N_LIB] * 5
    assert all(str(data["root"] / "darklib") in s for s in img.header["dark_sources"])
    z = _z(img, data["truth"])
    assert 0.9 < z.std() < 1.1 and abs(z.mean()) < 0.1, (z.std(), z.mean())
    # the library lacks 0.25 s: the error names the time
    code, _, err = _run(
        capsys,
        "merge",
        *data["frames"],
        "--calibration",
        data["cal"],
        "--dark-strategy",
        "master",
        "-o",
        tmp_path / "x.exr",
    )
    assert code != 0 and err.startswith("hdrcap: error:") and "exposure 0.25 s" in err and "dark library" in err


@pytest.mark.parametrize(
    "plan_kw, drop_dark, words",
    [
        ({"times": TIMES + [0.5], "darks": MIXED + ["model"]}, None, "planned exposure 0.5 s matches no frame"),
        ({"times": TIMES[:-1], "darks": MIXED[:-1]}, None, "exposure 1 s is not in the plan"),
        ({}, "0.016", "no dark frame with exposure time 0.016 s"),
        ({"darks": ["model"] * 5 + ["best"]}, None, "'best' is not matched, master or model"),
    ],
)
def test_merge_plan_errors_are_one_line(data, tmp_path, capsys, plan_kw, drop_dark, words):
    plan = _plan(tmp_path / "plan.json", **plan_kw)
    darks = [d for d in data["darks"] if drop_dark is None or f"_{drop_dark}" not in d.name]
    code, _, err = _run(
        capsys,
        "merge",
        *data["frames"],
        "--darks",
        *darks,
        "--calibration",
        data["cal"],
        "--plan",
        plan,
        "-o",
        tmp_path / "e.exr",
    )
    assert code != 0 and err.startswith("hdrcap: error:") and words in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "e.exr").exists()


def test_merge_takes_the_json_of_hdrcap_plan(data, tmp_path, capsys):
    """The contract end to end: `hdrcap plan --json` -> simulate its exposures -> merge --plan."""
    code, out, err = _run(
        capsys,
        "plan",
        "--camera",
        "camera-B",
        "--irradiance",
        data["root"] / "sim" / "truth.exr",
        "--target-snr-db",
        15,
        "--json",
    )
    assert code == 0, err
    (tmp_path / "plan.json").write_text(out)
    plan = json.loads(out)
    sim = tmp_path / "sim"
    code, _, err = _run(
        capsys,
        "simulate",
        "--camera",
        "camera-B",
        "--out",
        sim,
        "--size",
        "64x48",
        "--seed",
        "5",
        "--decades",
        "3",
        "--x-max",
        "2e4",
        "--darks",
        "--times",
        *sorted(set(plan["exposures"])),
    )
    assert code == 0, err
    code, _, err = _run(
        capsys,
        "merge",
        *sorted(sim.glob("frame_*.dng")),
        "--darks",
        *sorted(sim.glob("dark_*.dng")),
        "--camera",
        "camera-B",
        "--plan",
        tmp_path / "plan.json",
        "-o",
        tmp_path / "p.exr",
    )
    assert code == 0, err
    img = read_exr(tmp_path / "p.exr")
    p, m = img.header["planner"], img.header["merge"]
    assert p["decisions"] == plan["decisions"] and p["predicted_min_snr_db"] == plan["predicted_min_snr_db"]
    for name, value in p["options_from_plan"].items():
        assert m[name] == value
    assert set(p["options_from_plan"]) >= {"saturation", "prnu", "iterations"} and p["options_overridden"] == {}
    assert sorted(m["dark_strategies"]) == sorted(plan["darks"])


def test_dark_strategy_given_overrides_the_plan_and_bad_plans_fail(data, tmp_path, capsys):
    plan = _plan(tmp_path / "plan.json", darks=["model"] * 6, merge_options={"saturation": "threshold", "denoise": 1})
    code, _, err = _run(
        capsys,
        "merge",
        *data["frames"],
        "--darks",
        *data["darks"],
        "--calibration",
        data["cal"],
        "--plan",
        plan,
        "--dark-strategy",
        "matched",
        "-o",
        tmp_path / "o.exr",
    )
    assert code == 0, err
    assert "'denoise' is not one hdrcap merge knows" in err
    img = read_exr(tmp_path / "o.exr")
    p = img.header["planner"]
    assert img.header["merge"]["dark_strategies"] == ["matched"] * 6
    assert p["options_overridden"] == {"darks": {"plan": ["model"] * 6, "used": "matched"}}
    assert p["options_from_plan"] == {"saturation": "threshold"} and p["options_ignored"] == ["denoise"]
    (tmp_path / "bad.json").write_text("{not json")
    code, _, err = _run(
        capsys,
        "merge",
        *data["frames"],
        "--camera",
        "camera-B",
        "--plan",
        tmp_path / "bad.json",
        "-o",
        tmp_path / "b.exr",
    )
    assert code != 0 and err.startswith(f"hdrcap: error: {tmp_path / 'bad.json'}: not a plan")
