"""``hdrcap merge --bad-values mask``: impossible raw values (above the white level's ADC range)
written into one simulated DNG are refused by default; masked on request, they are left out of
that frame only: every other photosite is bit-identical to the merge of the clean frame, the
masked ones are estimated from the other frames (against the simulator's truth) and flagged,
never called saturated. Photosites masked in every frame carry no information (nexp = 0)."""

from __future__ import annotations

import json
import shutil
import struct

import numpy as np
import pytest

from hdrcap.cli import main
from hdrcap.mock_camera import SimulatedSensor, preset
from hdrcap.mock_camera.scenes import make_scene
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.exr import read_exr
from hdrcap.pipeline.io.raw import read_raw
from hdrcap.pipeline.merge.accumulator import merge_arrays
from hdrcap.pipeline.params import Calibration
from hdrcap.pipeline.schema import QUALITY_BITS

MASKED, SATURATED = QUALITY_BITS["masked"], QUALITY_BITS["saturated"]
N_BAD = 50
BAD = 2  # index of the corrupted frame (0.016 s)


def _strip_offset(blob: bytes) -> int:
    """Where the single strip of a little-endian simulator DNG's IFD0 starts (tag 273)."""
    ifd = struct.unpack_from("<I", blob, 4)[0]
    for i in range(struct.unpack_from("<H", blob, ifd)[0]):
        pos = ifd + 2 + 12 * i
        if struct.unpack_from("<H", blob, pos)[0] == 273:
            return struct.unpack_from("<I", blob, pos + 8)[0]
    raise KeyError(273)


def _run(capsys, *args):
    """``hdrcap ARGS`` in process: (exit status, stdout, stderr lines)."""
    rc = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, [line for line in err.splitlines() if line.strip()]


@pytest.fixture(scope="module")
def bracket(tmp_path_factory):
    """A simulated camera-B bracket (64x48, 10 bit) and a copy whose frame BAD has N_BAD
    photosites above the white level (1024..65535 DN); the photosites' (row, col)."""
    root = tmp_path_factory.mktemp("badvalues")
    sim = root / "sim"
    assert main(["simulate", "--camera", "camera-B", "--out", str(sim), "--size", "64x48", "--seed", "3"]) == 0
    clean = sorted(sim.glob("frame_*.dng"))
    bad_dir = root / "bad"
    bad_dir.mkdir()
    frames = [shutil.copy(p, bad_dir / p.name) for p in clean]
    rng = np.random.default_rng(11)
    flat = rng.choice(64 * 48, N_BAD, replace=False)
    values = rng.integers(1024, 65536, N_BAD)
    blob = bytearray(frames[BAD].read_bytes())
    start = _strip_offset(bytes(blob))
    for k, v in zip(flat, values):
        struct.pack_into("<H", blob, start + 2 * int(k), int(v))
    frames[BAD].write_bytes(bytes(blob))
    rows, cols = np.unravel_index(flat, (48, 64))
    return sim, clean, frames, (rows, cols)


def test_read_raw_masks_exactly_the_impossible_values(bracket):
    _sim, clean, frames, (rows, cols) = bracket
    with pytest.raises(InputError, match=rf"{frames[BAD].name}: {N_BAD} photosites above the white level"):
        read_raw(frames[BAD])
    fr = read_raw(frames[BAD], bad_values="mask")
    expect = np.zeros((48, 64), bool)
    expect[rows, cols] = True
    np.testing.assert_array_equal(fr.masked, expect)
    assert fr.n_masked == N_BAD
    np.testing.assert_array_equal(fr.data[~expect], read_raw(clean[BAD]).data[~expect])
    assert read_raw(clean[BAD], bad_values="mask").masked is None
    with pytest.raises(InputError, match="bad values must be refused or masked"):
        read_raw(clean[BAD], bad_values="ignore")


def test_problems_that_are_not_per_photosite_are_still_refused(bracket, tmp_path):
    """A black level above the white level is no pixel value to mask."""
    _sim, clean, _frames, _rc = bracket
    blob = clean[0].read_bytes()
    pos = blob.index(struct.pack("<II", 32, 1))  # the BlackLevel rational (32/1 DN)
    bad = tmp_path / "black.dng"
    out = bytearray(blob)
    struct.pack_into("<II", out, pos, 2000, 1)
    bad.write_bytes(bytes(out))
    with pytest.raises(InputError, match="black.dng: black level 2000.0 DN is not between 0 and the white level"):
        read_raw(bad, bad_values="mask")


def test_merge_refuses_by_default_with_one_line(bracket, tmp_path, capsys):
    _sim, _clean, frames, _rc = bracket
    rc, _out, err = _run(capsys, "merge", *frames, "--camera", "camera-B", "-o", tmp_path / "m.exr")
    assert rc == 2 and len(err) == 1, err
    assert err[0].startswith(f"hdrcap: error: {frames[BAD]}: {N_BAD} photosites above the white level"), err
    assert not (tmp_path / "m.exr").exists()


@pytest.mark.parametrize("times", ["nominal", "effective"])
def test_masked_merge_against_the_clean_one_and_the_truth(bracket, tmp_path, capsys, times):
    sim, clean, frames, (rows, cols) = bracket
    common = ("--camera", "camera-B", "--exposure-times", times)
    assert _run(capsys, "merge", *clean, *common, "-o", tmp_path / "clean.exr")[0] == 0
    rc, out, err = _run(capsys, "merge", *frames, *common, "--bad-values", "mask", "-o", tmp_path / "m.exr", "--json")
    assert rc == 0 and json.loads(out)["masked_photosites"] == N_BAD
    warned = [line for line in err if "masked" in line]
    assert len(warned) == 1 and str(frames[BAD]) in warned[0] and f" {N_BAD} photosites" in warned[0], err
    ref, img = read_exr(tmp_path / "clean.exr").channels, read_exr(tmp_path / "m.exr")
    ch = img.channels
    assert img.header["masked_values"] == {str(f): (N_BAD if i == BAD else 0) for i, f in enumerate(frames)}
    masked = np.zeros((48, 64), bool)
    masked[rows, cols] = True
    q = ch["quality"].astype(np.uint8)
    np.testing.assert_array_equal((q & MASKED) != 0, masked)
    assert set(ch) == set(ref)  # a preset has no standard errors: no sigma_calibration in either
    for name in ("irradiance", "sigma", "nexp"):
        if times == "nominal":  # per photosite independent: the others are bit for bit the clean merge
            np.testing.assert_array_equal(ch[name][~masked], ref[name][~masked], err_msg=name)
        else:  # the bracket's exposure-time estimate loses 50 of its photosites in one frame
            np.testing.assert_allclose(ch[name][~masked], ref[name][~masked], rtol=1e-3, err_msg=name)
    np.testing.assert_array_equal(q[~masked], ref["quality"][~masked].astype(np.uint8))
    # the masked photosites: estimated from the other frames, against the simulator's truth
    truth = read_exr(sim / "truth.exr").channels["irradiance"]
    nexp, irr, sig = ch["nexp"][masked], ch["irradiance"][masked], ch["sigma"][masked]
    assert np.isfinite(irr).all() and np.isfinite(sig).all()
    assert np.all(nexp <= ref["nexp"][masked]) and np.all(nexp >= ref["nexp"][masked] - 1)
    ok = nexp > 0
    assert ok.sum() > 0.8 * N_BAD, int(ok.sum())
    z = (irr[ok] - truth[masked][ok]) / sig[ok]
    assert np.all(np.abs(z) < 6), z
    assert np.all(sig[ok] > 0)
    # saturated only where every frame that was not masked is saturated
    np.testing.assert_array_equal((q[masked] & SATURATED) != 0, nexp == 0)
    assert img.header["merge"]["masked_photosites"] == N_BAD
    assert img.header["merge"]["masked_per_frame"] == [N_BAD if i == BAD else 0 for i in range(len(frames))]


def test_mask_refused_with_chunks_baselines_and_self_calibration(bracket, tmp_path, capsys):
    _sim, _clean, frames, _rc = bracket
    out = tmp_path / "m.exr"
    for extra, why in (
        (("--camera", "camera-B", "--chunks", "16"), "--chunks 16: tiled merges refuse bad values"),
        (("--camera", "camera-B", "--weighting", "debevec"), "--bad-values mask works with --weighting optimal"),
        ((), "--bad-values mask needs --calibration or --camera"),
    ):
        rc, _o, err = _run(capsys, "merge", *frames, *extra, "--bad-values", "mask", "-o", out)
        assert rc == 2 and len(err) == 1 and why in err[0], err
    assert not out.exists()


# ------------------------------------------------------------------------------ array level
@pytest.fixture(scope="module")
def arrays():
    """A camera-B bracket of a gradient (4 decades) at four exact times (the simulator's
    physics: Poisson electrons, Gaussian read noise, rounding, clipping), its nominal
    calibration (no PRNU map: the comparisons below are merge against merge) and the truth."""
    spec = preset("camera-B", shutter_error=0.0, shutter_jitter=0.0)
    shape = (32, 40)
    sensor = SimulatedSensor(spec, shape, seed=4)
    X = make_scene("gradient", shape, 4.0, 2e5)
    times = (0.001, 0.01, 0.1, 1.0)
    rng = np.random.default_rng(4)
    values = [sensor.expose(X, t, rng=rng) for t in times]
    return Calibration(params=spec.nominal_params()), X, times, values


def test_masked_everywhere_and_saturated_elsewhere(arrays):
    cal, X, times, values = arrays
    masks = [np.zeros(values[0].shape, bool) for _ in values]
    for m in masks:
        m[0, :4] = True  # masked in every frame: no information
    masks[0][-1, -4:] = True  # brightest corner, masked in the shortest frame only
    res = merge_arrays(values, times, cal, masks=masks, exposure_times="nominal")
    q = res.quality
    assert np.all(res.nexp[0, :4] == 0) and np.all(q[0, :4] == MASKED)
    assert np.all(res.irradiance[0, :4] == 0) and np.all(res.sigma[0, :4] == 0)
    assert res.info["masked_everywhere"] == 4 and res.info["masked_photosites"] == 8
    # the masked photosites equal the merge without the masked frame (nexp exactly)
    rest = merge_arrays(values[1:], times[1:], cal, exposure_times="nominal")
    corner = (slice(-1, None), slice(-4, None))
    np.testing.assert_array_equal(res.nexp[corner], rest.nexp[corner])
    np.testing.assert_allclose(res.irradiance[corner], rest.irradiance[corner], rtol=1e-5)
    sat = rest.nexp[corner] == 0  # saturated in every frame left: a lower bound, flagged both ways
    np.testing.assert_array_equal((q[corner] & SATURATED) != 0, sat)
    assert np.all(q[corner] & MASKED)
    assert np.all(res.irradiance[corner][sat] <= X[corner][sat])


@pytest.mark.parametrize("saturation", ["threshold", "probabilistic"])
def test_a_masked_sample_is_no_sample_not_a_saturated_one(arrays, saturation):
    """Under the censored likelihood a saturated sample is information (X above a bound); a
    masked one must be none: the merge equals the merge without that frame."""
    cal, _X, times, values = arrays
    mask = np.zeros(values[0].shape, bool)
    mask[::3, ::5] = True
    masks = [None, None, mask, None]
    res = merge_arrays(values, times, cal, masks=masks, exposure_times="nominal", saturation=saturation)
    rest = merge_arrays(
        [v for i, v in enumerate(values) if i != 2],
        [t for i, t in enumerate(times) if i != 2],
        cal,
        exposure_times="nominal",
        saturation=saturation,
    )
    np.testing.assert_array_equal(res.nexp[mask], rest.nexp[mask])
    np.testing.assert_allclose(res.irradiance[mask], rest.irradiance[mask], rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(res.sigma[mask], rest.sigma[mask], rtol=1e-4, atol=1e-3)
    assert not np.any(res.quality[mask] & SATURATED & (res.nexp[mask] > 0))
