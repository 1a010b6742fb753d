"""Calibration (Sec. 6, EMVA 1288) against the simulator's truth, outliers and bad input.

Every expectation comes from the simulator's physics (the true g, mu_R, sigma2_R, v_sat, a_j,
D), from a shot-noise limit computed here from those true values, or from the seed-to-seed
spread; never from the calibration code's own output.
"""

from __future__ import annotations

import numpy as np
import pytest

from hdrcap.mock_camera import PRESETS, SimulatedSensor
from hdrcap.mock_camera.sensor import SensorSpec
from hdrcap.pipeline.calibration import (
    PixelStack,
    calibrate,
    load_calibration,
    pair_statistics,
    photon_transfer_gain,
    save_calibration,
)
from hdrcap.pipeline.errors import InputError, OutputExistsError
from hdrcap.pipeline.io.raw import RawFrame

SHAPE = (256, 256)


def shots(sensor, X, t, n, rng, kind, dark=False, start=0, hits=None):
    """Yield n simulated RawFrames (lazily, as a camera would deliver them)."""
    for i in range(n):
        data = sensor.expose(X, t, dark=dark, rng=rng)
        if hits is not None:
            data = hits(data, rng)
        yield RawFrame(data, t, path=f"{kind}_{start + i:03d}.dng", white_level=sensor.spec.white_level)


def paper_set(spec, seed, shape=SHAPE, n_flats=36, flat_fraction=0.75, sensor_seed=None, hits=None):
    """Sec. 7 of the paper: 2 bias, 1 saturation and 36 flat frames."""
    sensor = SimulatedSensor(spec, shape, seed=seed if sensor_seed is None else sensor_seed)
    rng = np.random.default_rng([seed, 77])
    nominal = spec.nominal_params()
    t = 0.01
    X = flat_fraction * (nominal.v_sat - spec.mu_R) / spec.g / t
    bias = shots(sensor, 0.0, 1e-4, 2, rng, "bias", dark=True, hits=hits)
    sat = shots(sensor, X, 10 * t, 1, rng, "saturation")
    flats = shots(sensor, X, t, n_flats, rng, "flat", hits=hits)
    return sensor, bias, sat, flats, X, t


@pytest.mark.parametrize("camera", ["camera-A", "camera-B"])
def test_paper_frame_counts_meet_tolerances(camera):
    spec = PRESETS[camera]
    sensor, bias, sat, flats, X, t = paper_set(spec, seed=3)
    cal = calibrate(bias, sat, flats, white_level=spec.white_level)
    p, truth = cal.params, spec.nominal_params()
    assert p.g == pytest.approx(spec.g, rel=0.01)
    assert abs(p.mu_R - spec.mu_R) < 0.05
    assert p.sigma2_R == pytest.approx(spec.sigma2_R, rel=0.03)
    assert p.v_sat == pytest.approx(truth.v_sat, rel=0.01)
    assert cal.provenance["frame_counts"] == {"bias": 2, "saturation": 1, "flat": 36, "dark": 0}
    # a_j against the true PRNU (normalised to mean 1 like Eq. 14)
    a_true = sensor.prnu / sensor.prnu.mean()
    rms = float(np.sqrt(np.mean((cal.prnu - a_true) ** 2)))
    # shot-noise limit from the true model: each flat has variance g*s + sigma2_R at level s
    # (DN above bias); the two-frame offset map adds sigma2_R / 2 common to all flats
    s = spec.g * X * t
    limit = np.sqrt((spec.g * s + spec.sigma2_R) / (36 * s**2) + spec.sigma2_R / (2 * s**2))
    assert rms < 1.5 * limit, (rms, limit)
    assert rms > 0.7 * limit  # the map is not smoothed or otherwise too good to be true
    # the stated a_j error agrees with the real one
    stated = float(np.sqrt(np.mean(cal.prnu_stderr.astype(float) ** 2)))
    assert stated == pytest.approx(rms, rel=0.15)
    assert cal.provenance["prnu_std"] == pytest.approx(spec.prnu, rel=0.1)


def test_stated_stderr_matches_spread_over_seeds():
    spec = PRESETS["camera-B"]
    est = {"g": [], "mu_R": [], "sigma2_R": [], "v_sat": []}
    se = {k: [] for k in est}
    for seed in range(6):
        _, bias, sat, flats, _, _ = paper_set(spec, seed=seed, shape=(128, 128), sensor_seed=0, flat_fraction=0.6)
        cal = calibrate(bias, shots_sat_unclipped(spec, seed), flats, white_level=spec.white_level)
        for k in est:
            est[k].append(getattr(cal.params, k))
            se[k].append(cal.stderr[k])
    for k in ("g", "mu_R", "sigma2_R", "v_sat"):
        spread = float(np.std(est[k], ddof=1))
        stated = float(np.mean(se[k]))
        # six seeds: the sample std is within a factor ~2 of the truth with >99 % probability
        assert 0.4 * stated < spread < 2.2 * stated, (k, spread, stated)


def shots_sat_unclipped(spec, seed):
    """A saturation frame whose spread is read noise (camera-B's ADC clips: use its full well
    with a larger white level so that mean - 3 std is a statistic, not a constant)."""
    big = spec.replace(bits=12, full_well=1000.0 / spec.g)
    sensor = SimulatedSensor(big, (128, 128), seed=0)
    rng = np.random.default_rng([seed, 5])
    return shots(sensor, 1e6, 1.0, 1, rng, "saturation")


def test_photon_transfer_series_is_default_and_accurate():
    spec = PRESETS["camera-A"]
    sensor = SimulatedSensor(spec, (128, 128), seed=4)
    rng = np.random.default_rng(4)
    span = spec.nominal_params().v_sat - spec.mu_R
    X = span / spec.g / 0.01

    def flats():
        for f in np.linspace(0.05, 0.95, 12):
            yield from shots(sensor, X, 0.01 * f, 2, rng, f"ptc{f:.2f}")

    cal = calibrate(
        shots(sensor, 0, 1e-4, 2, rng, "bias", dark=True),
        shots(sensor, X, 0.1, 1, rng, "sat"),
        flats(),
        white_level=spec.white_level,
    )
    assert "photon-transfer" in cal.provenance["calibration"]["gain_method"]
    assert cal.params.g == pytest.approx(spec.g, rel=0.01)
    assert abs(cal.params.g - spec.g) < 4 * cal.stderr["g"]
    ptc = cal.provenance["calibration"]["ptc"]
    used = np.array(ptc["used"])
    assert used.sum() == 8  # levels 5 %..70 % of saturation (0.05 + k * 0.0818 <= 0.70)


def test_pair_variance_formula_and_regression_through_origin():
    rng = np.random.default_rng(1)
    a = rng.normal(100.0, 3.0, (200, 200))
    b = rng.normal(103.0, 3.0, (200, 200))  # a level change between the frames must not count
    ps = pair_statistics(a, b, clip=None)
    assert ps.variance == pytest.approx(9.0, rel=0.03)
    assert abs(ps.variance - 9.0) < 4 * ps.variance_stderr
    x = np.array([100.0, 200, 300, 400, 2000])
    fit = photon_transfer_gain(x, 0.25 * x, saturation=1000.0)
    assert fit.g == pytest.approx(0.25) and fit.used.tolist() == [True] * 4 + [False]


def test_dark_current_mean_and_map_from_six_times():
    spec = PRESETS["camera-B"].replace(dark_current=20.0, dcnu=0.3)
    sensor = SimulatedSensor(spec, (128, 128), seed=2)
    rng = np.random.default_rng(2)
    nominal = spec.nominal_params()
    X = 0.6 * (nominal.v_sat - spec.mu_R) / spec.g / 0.01

    def darks():
        for t in (0.5, 1, 2, 4, 8, 16):
            yield from shots(sensor, 0, t, 4, rng, f"dark{t}", dark=True)

    masters = []
    cal = calibrate(
        shots(sensor, 0, 1e-4, 2, rng, "bias", dark=True),
        shots(sensor, X, 0.1, 1, rng, "sat"),
        shots(sensor, X, 0.01, 4, rng, "flat"),
        darks(),
        white_level=spec.white_level,
        dark_sink=masters.append,
    )
    true_map = sensor.dark_current_map()
    D_true = float(np.mean(true_map))
    assert abs(cal.params.dark_current - D_true) < 4 * cal.stderr["dark_current"]
    assert cal.params.dark_current == pytest.approx(D_true, rel=0.05)
    # per-photosite map: 16 s x 20 e-/s = 320 e- of signal, shot noise ~ 8 %
    corr = np.corrcoef(cal.dark_current_map.ravel(), true_map.ravel())[0, 1]
    assert corr > 0.9
    assert [m.n_frames for m in masters] == [4] * 6
    assert [m.exposure_time for m in masters] == [0.5, 1, 2, 4, 8, 16]


# --------------------------------------------------------------------------- outliers


def cosmic_rays(n=100, lo=300.0, hi=5000.0):
    def hit(data, rng):
        out = data.astype(np.int64)
        idx = rng.choice(out.size, n, replace=False)
        out.flat[idx] += rng.uniform(lo, hi, n).astype(np.int64)
        return np.clip(out, 0, 65535).astype(np.uint16)

    return hit


CR_SPEC = SensorSpec(
    name="cr",
    g=0.2,
    mu_R=200.0,
    sigma2_R=(10 * 0.2) ** 2,
    bits=16,
    full_well=2e5,
    dark_current=0.0,
    dcnu=0.0,
    prnu=0.01,
)


def _cosmic_run(clip):
    sensor = SimulatedSensor(CR_SPEC, SHAPE, seed=9)
    rng = np.random.default_rng(9)
    t = 1.0
    X = 1000.0 / CR_SPEC.g  # flats at ~1000 DN above bias
    hits = cosmic_rays()
    return calibrate(
        shots(sensor, 0, 1e-4, 2, rng, "bias", dark=True, hits=hits),
        None,
        shots(sensor, X, t, 4, rng, "flat", hits=hits),
        clip=clip,
        white_level=65535,
    )


def test_cosmic_rays_are_clipped():
    """Gain 5 e-/DN, read noise 10 e-, flats ~1000 DN, 100 cosmic rays per frame."""
    cal = _cosmic_run(clip=5.0)
    gain_e_per_dn = 1 / cal.params.g
    read_noise_e = np.sqrt(cal.params.sigma2_R) / cal.params.g
    assert gain_e_per_dn == pytest.approx(5.0, rel=0.02)
    assert read_noise_e == pytest.approx(10.0, rel=0.02)
    raw = _cosmic_run(clip=None)  # the same frames without clipping come out badly wrong
    assert abs(np.sqrt(raw.params.sigma2_R) / raw.params.g / 10.0 - 1) > 0.5
    assert abs(1 / raw.params.g / 5.0 - 1) > 0.1


def test_pixel_stack_rejects_one_hit_per_photosite_keeps_hot_pixels():
    rng = np.random.default_rng(0)
    truth = 1000.0 + 50.0 * rng.standard_normal((64, 64))
    truth[5, 5] = 20000.0  # a stable hot pixel is signal, not an outlier
    stack = PixelStack(truth.shape)
    frames = []
    for i in range(10):
        f = truth + 10.0 * rng.standard_normal(truth.shape)
        if i == 3:
            f[10, 10] += 5000.0  # cosmic ray
        frames.append(f)
        stack.add(f)
    mean, err, rejected = stack.result()
    assert abs(mean[10, 10] - truth[10, 10]) < 5 * 10 / np.sqrt(9)
    assert abs(mean[5, 5] - truth[5, 5]) < 5 * 10 / np.sqrt(10)
    assert rejected < 20
    assert np.sqrt(np.mean(err**2)) == pytest.approx(10 / np.sqrt(10), rel=0.1)


# --------------------------------------------------------------------------- bad input


def _frames(arrs, kind, t=0.01):
    return [RawFrame(np.asarray(a, np.uint16), t, path=f"{kind}_{i}.dng") for i, a in enumerate(arrs)]


def _good(seed=0):
    spec = PRESETS["camera-B"]
    sensor = SimulatedSensor(spec, (64, 64), seed=seed)
    rng = np.random.default_rng(seed)
    X = 600 / spec.g / 0.01
    bias = [sensor.expose(0, 1e-4, dark=True, rng=rng) for _ in range(2)]
    sat = [sensor.expose(X, 1.0, rng=rng)]
    flats = [sensor.expose(X, 0.01, rng=rng) for _ in range(4)]
    return sensor, bias, sat, flats, X


def test_bad_inputs_name_the_frame():
    sensor, bias, sat, flats, X = _good()
    ok = dict(saturation=_frames(sat, "sat", 1.0), white_level=1023)
    # mixed size
    bad = flats[:3] + [flats[3][:32, :]]
    with pytest.raises(InputError, match=r"flat_3\.dng: size 64x32 differs"):
        calibrate(_frames(bias, "bias", 1e-4), flats=_frames(bad, "flat"), **ok)
    # saturated flat
    bad = flats[:3] + [sensor.expose(X, 1.0)]
    with pytest.raises(InputError, match=r"flat_3\.dng: flat field is saturated"):
        calibrate(_frames(bias, "bias", 1e-4), flats=_frames(bad, "flat"), **ok)
    # dark flat
    bad = [sensor.expose(0, 0.01, dark=True)] + flats[1:]
    with pytest.raises(InputError, match=r"flat_0\.dng: flat field is dark"):
        calibrate(_frames(bias, "bias", 1e-4), flats=_frames(bad, "flat"), **ok)
    # bias frame with signal
    lit = [bias[0], sensor.expose(X, 0.0005)]
    with pytest.raises(InputError, match=r"bias_1\.dng: bias frame with signal"):
        calibrate(_frames(lit, "bias", 1e-4), flats=_frames(flats, "flat"), **ok)
    # bias frames of mixed exposure
    mixed = _frames(bias, "bias", 1e-4)
    mixed[1] = RawFrame(bias[1], 0.5, path="bias_1.dng")
    with pytest.raises(InputError, match=r"bias_1\.dng: bias exposure time"):
        calibrate(mixed, flats=_frames(flats, "flat"), **ok)
    # too few frames for the asked estimate
    with pytest.raises(InputError, match="at least two flat fields at the same exposure time"):
        calibrate(_frames(bias, "bias", 1e-4), flats=_frames(flats[:1], "flat"), **ok)
    with pytest.raises(InputError, match=">= 6 exposure times"):
        calibrate(
            _frames(bias, "bias", 1e-4),
            flats=_frames(flats, "flat"),
            darks=[RawFrame(sensor.expose(0, t, dark=True), t, path=f"d{t}") for t in (1, 2, 4)],
            **ok,
        )
    with pytest.raises(InputError, match="no bias frames"):
        calibrate([], flats=_frames(flats, "flat"), **ok)
    with pytest.raises(InputError, match="photon-transfer regression needs"):
        calibrate(_frames(bias, "bias", 1e-4), flats=_frames(flats, "flat"), gain_method="ptc", **ok)


# --------------------------------------------------------------------------- the file


def test_calibration_file_round_trip_and_checks(tmp_path):
    sensor, bias, sat, flats, X = _good(1)
    cal = calibrate(
        _frames(bias, "bias", 1e-4),
        _frames(sat, "sat", 1.0),
        _frames(flats, "flat"),
        white_level=1023,
        provenance={"camera": "cam", "serial": "S1", "iso": 400, "temperature": 21.5},
    )
    path = tmp_path / "my.calibration"
    save_calibration(path, cal)
    back = load_calibration(path)
    assert back.params == cal.params
    assert back.stderr == cal.stderr
    np.testing.assert_array_equal(back.prnu, cal.prnu)
    np.testing.assert_array_equal(back.bias_map, cal.bias_map)
    np.testing.assert_array_equal(back.prnu_stderr, cal.prnu_stderr)
    for key in ("camera", "serial", "iso", "temperature", "frame_counts", "created", "hdrcap_version"):
        assert key in back.provenance
    with pytest.raises(OutputExistsError):
        save_calibration(path, cal)
    save_calibration(path, cal, force=True)
    # version, shape and format checks
    import json

    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(bytes(arrays["metadata"]).decode())
    for change, pattern in (
        ({"version": 99}, "version 99 is not supported"),
        ({"shape": [3, 3]}, "has shape"),
        ({"format": "other"}, "not an hdrcap calibration file"),
    ):
        m = dict(meta, **change)
        bad = tmp_path / "bad.npz"
        np.savez(bad, **{**arrays, "metadata": np.frombuffer(json.dumps(m).encode(), np.uint8)})
        with pytest.raises(InputError, match=pattern):
            load_calibration(bad)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="junk.npz"):
        load_calibration(tmp_path / "junk.npz")
    from hdrcap.acquire.camera.model import camera_model

    assert camera_model(path).params == cal.params


def test_dark_library(tmp_path):
    from hdrcap.pipeline.calibration.darklibrary import DarkLibrary

    lib = DarkLibrary(tmp_path / "lib")
    assert lib.entries() == []
    m = np.full((4, 4), 130.0, np.float32)
    lib.add(m, 16, camera="cam", iso=400, exposure_time=2.0, temperature=20.0)
    lib.add(m + 1, 8, camera="cam", iso=400, exposure_time=2.0, temperature=30.0)
    lib.add(m + 2, 8, camera="cam", iso=800, exposure_time=2.0, temperature=20.0)
    with pytest.raises(InputError, match="exists"):
        lib.add(m, 4, camera="cam", iso=400, exposure_time=2.0, temperature=20.0)
    e = lib.find(camera="cam", iso=400, exposure_time=2.0, temperature=20.6)
    data, n = lib.load(e)
    assert n == 16 and float(data.mean()) == 130.0
    assert lib.find(camera="cam", iso=400, exposure_time=2.0, temperature=25.0) is None
    assert lib.find(camera="cam", iso=400, exposure_time=4.0) is None
    assert len(DarkLibrary(tmp_path / "lib").entries()) == 3


def test_emva_stage_on_a_simulated_descriptor(tmp_path):
    """parse -> data -> results on an EMVA 1288 data set written from the simulator (runs
    everywhere; the real reference set is tested in tests/cli/test_calibrate.py)."""
    from PIL import Image

    from hdrcap.pipeline.calibration.emva import emva_calibration, emva_data, emva_results
    from hdrcap.pipeline.io.emva_descriptor import read_emva_descriptor

    spec = PRESETS["camera-A"].replace(dark_current=50.0)
    sensor = SimulatedSensor(spec, (96, 96), seed=6)
    rng = np.random.default_rng(6)
    X = 3500 / spec.g / 0.02  # reaches the ADC/full well beyond t = 0.02 s
    (tmp_path / "images").mkdir()
    lines = ["v 3.0", f"n {spec.bits} 96 96"]
    k = 0

    def put(data):
        nonlocal k
        name = f"images/img_{k:04d}.png"
        Image.fromarray(data).save(tmp_path / name)
        lines.append("i " + name.replace("/", "\\"))
        k += 1

    for t in np.linspace(0.0005, 0.024, 16):
        lines.append(f"b {t * 1e9:.1f} {X * t:.1f}")
        for _ in range(2):
            put(sensor.expose(X, t, rng=rng))
        lines.append(f"d {t * 1e9:.1f}")
        for _ in range(2):
            put(sensor.expose(0, t, dark=True, rng=rng))
    for kind in ("b", "d"):
        lines.append(f"{kind} {0.01 * 1e9:.1f}" + (f" {X * 0.01:.1f}" if kind == "b" else ""))
        for _ in range(16):
            put(sensor.expose(X if kind == "b" else 0, 0.01, dark=kind == "d", rng=rng))
    (tmp_path / "EMVA1288_Data.txt").write_text("\n".join(lines) + "\n")
    data = emva_data(read_emva_descriptor(tmp_path / "EMVA1288_Data.txt"))
    res = emva_results(data)
    assert res.K == pytest.approx(spec.g, rel=0.03)
    assert res.sigma_y_dark**2 == pytest.approx(spec.sigma2_R, rel=0.1)
    assert res.PRNU1288 == pytest.approx(100 * spec.prnu, rel=0.15)
    assert res.u_I_mean == pytest.approx(float(sensor.dark_current_map().mean()), rel=0.2)
    assert res.QE == pytest.approx(100.0, rel=0.05)  # the simulator's photons are electrons
    cal = emva_calibration(data, res)
    a_true = sensor.prnu / sensor.prnu.mean()
    assert np.sqrt(np.mean((cal.prnu - a_true) ** 2)) < 1.5 * np.sqrt(np.mean(cal.prnu_stderr.astype(float) ** 2))


def test_hot_pixels_do_not_bias_dark_current_but_stay_in_the_map():
    spec = PRESETS["camera-B"].replace(dark_current=5.0, dcnu=0.1, hot_pixel_fraction=0.003, hot_pixel_factor=100.0)
    sensor = SimulatedSensor(spec, (128, 128), seed=8)
    rng = np.random.default_rng(8)
    X = 600 / spec.g / 0.01

    def darks():
        for t in (0.05, 0.1, 0.2, 0.4, 0.7, 1.0):  # hot pixels (500 e-/s) stay below the ADC limit
            yield from shots(sensor, 0, t, 4, rng, f"dark{t}", dark=True)

    cal = calibrate(
        shots(sensor, 0, 1e-4, 2, rng, "bias", dark=True),
        shots(sensor, X, 0.1, 1, rng, "sat"),
        shots(sensor, X, 0.01, 4, rng, "flat"),
        darks(),
        white_level=spec.white_level,
    )
    true_map = sensor.dark_current_map()
    hot = true_map > 50
    assert 20 < hot.sum() < 100
    D_cold = float(true_map[~hot].mean())
    assert float(true_map.mean()) > 1.25 * D_cold  # averaging hot pixels in would be a gross error
    assert cal.params.dark_current == pytest.approx(D_cold, rel=0.05)
    np.testing.assert_allclose(cal.dark_current_map[hot], true_map[hot], rtol=0.1)


def test_ptc_gain_and_dark_current_stderr_match_seed_spread():
    spec = PRESETS["camera-B"].replace(dark_current=20.0)
    sensor = SimulatedSensor(spec, (96, 96), seed=0)
    X = (spec.nominal_params().v_sat - spec.mu_R) / spec.g / 0.01
    est = {"g": [], "dark_current": []}
    se = {k: [] for k in est}
    for seed in range(8):
        rng = np.random.default_rng([seed, 11])

        def flats(rng=rng):
            for f in np.linspace(0.05, 0.85, 12):
                yield from shots(sensor, X, 0.01 * f, 2, rng, f"ptc{f:.2f}")

        def darks(rng=rng):
            for t in (0.5, 1, 2, 4, 8, 16):
                yield from shots(sensor, 0, t, 2, rng, f"dark{t}", dark=True)

        cal = calibrate(
            shots(sensor, 0, 1e-4, 2, rng, "bias", dark=True),
            shots(sensor, X, 0.1, 1, rng, "sat"),
            flats(),
            darks(),
            white_level=spec.white_level,
        )
        assert "photon-transfer" in cal.provenance["calibration"]["gain_method"]
        for k in est:
            est[k].append(getattr(cal.params, k))
            se[k].append(cal.stderr[k])
    truth = {"g": spec.g, "dark_current": float(sensor.dark_current_map().mean())}
    for k in est:
        spread, stated = float(np.std(est[k], ddof=1)), float(np.mean(se[k]))
        assert 0.4 * stated < spread < 2.2 * stated, (k, spread, stated)
        assert abs(np.mean(est[k]) - truth[k]) < 4 * stated / np.sqrt(8)


def test_per_photosite_saturation_map_when_data_allow():
    spec = PRESETS["camera-A"].replace(offset_fpn=6.0)
    sensor = SimulatedSensor(spec, (96, 96), seed=12)
    rng = np.random.default_rng(12)
    X = 0.6 * (spec.nominal_params().v_sat - spec.mu_R) / spec.g / 0.01
    run = dict(flats=shots(sensor, X, 0.01, 4, rng, "flat"), white_level=spec.white_level)
    one = calibrate(shots(sensor, 0, 1e-4, 2, rng, "bias", dark=True), shots(sensor, X, 0.1, 1, rng, "sat"), **run)
    assert one.saturation_map is None  # one frame cannot give a per-photosite limit
    run["flats"] = shots(sensor, X, 0.01, 4, rng, "flat")
    cal = calibrate(shots(sensor, 0, 1e-4, 2, rng, "bias", dark=True), shots(sensor, X, 0.1, 6, rng, "sat"), **run)
    truth = spec.mu_R + spec.g * spec.full_well + sensor.offset - 3 * np.sqrt(spec.sigma2_R)
    err = cal.saturation_map - truth
    assert abs(float(err.mean())) < 0.5
    assert float(np.sqrt(np.mean(err**2))) < 2.0 < float(np.std(sensor.offset))  # resolves the 6 DN pattern
    assert cal.params.v_sat < float(np.mean(truth))  # the scalar limit also covers the offset spread


def test_flat_pairs_in_order_and_a_pair_censored_away_is_skipped():
    """estimate_flats computes the pairs' statistics in a thread of its own: the pairs come back
    in the order of the files, each with the variance of its two frames (g mu + sigma_R^2 of
    the simulated Poisson counts, within 3 standard errors), and a pair whose photosites are all
    censored near v_sat is skipped with its files and reason, not lost or reordered."""
    from hdrcap.pipeline.calibration.flats import estimate_flats

    rng = np.random.default_rng(4)
    shape, bias, g, s2, v_sat = (32, 40), 100.0, 0.5, 4.0, 4000.0
    frames, expect = [], []
    for k, (t, electrons) in enumerate(((0.01, 2000.0), (0.02, 3000.0), (0.03, None), (0.04, 5000.0))):
        for j in range(2):
            if electrons is None:  # 45 % clipped at v_sat, the rest within a few DN of it
                data = np.where(rng.random(shape) < 0.45, v_sat, v_sat - 1.0 - rng.integers(0, 2, shape))
            else:
                data = bias + g * rng.poisson(electrons, shape) + rng.normal(0.0, np.sqrt(s2), shape)
            frames.append(RawFrame(data.astype(np.float32), t, path=f"flat_{k}_{j}.dng"))
        expect.append(None if electrons is None else g * g * electrons + s2)
    res = estimate_flats(frames, bias, v_sat, s2)
    assert [p.exposure_time for p in res.pairs] == [0.01, 0.02, 0.04]
    for p, want in zip(res.pairs, [e for e in expect if e is not None]):
        assert abs(p.variance - want) < 3.0 * p.variance_stderr + 1e-9, (p.exposure_time, p.variance, want)
    assert [s["files"] for s in res.skipped_pairs] == [["flat_2_0.dng", "flat_2_1.dng"]]
    assert res.skipped_pairs[0]["t"] == 0.03 and "survive" in res.skipped_pairs[0]["reason"]
