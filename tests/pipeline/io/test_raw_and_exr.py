"""Raw and EXR I/O: DNG round trip through rawpy, EXIF, EXR channels and attributes,
EMVA descriptor parsing, atomic no-clobber writes."""

import json
from fractions import Fraction

import numpy as np
import pytest

from hdrcap.mock_camera.dng import exposure_rational
from hdrcap.pipeline.errors import InputError, OutputExistsError
from hdrcap.pipeline.io.emva_descriptor import read_emva_descriptor
from hdrcap.pipeline.io.exr import ExrContent, read_exr, write_exr
from hdrcap.pipeline.io.files import atomic_output
from hdrcap.pipeline.io.raw import check_frames, read_frame, read_raw
from tests.helpers.dng import write_test_dng as _dng


@pytest.mark.parametrize("cfa", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_dng_round_trip_bit_exact(tmp_path, cfa):
    rng = np.random.default_rng(1)
    data = rng.integers(0, 4096, (34, 52), dtype=np.uint16)  # 0 .. the white level
    fr = read_raw(_dng(tmp_path / "a.dng", data, cfa=cfa))
    assert fr.data.dtype == np.uint16 and np.array_equal(fr.data, data)
    assert fr.cfa_pattern == cfa
    assert fr.black_level == 128 and fr.white_level == 4095
    assert fr.camera == "Acme Sim 1"
    assert fr.timestamp.startswith("2026:01:02")


@pytest.mark.parametrize("t", [1e-6, 1 / 8000, 1 / 3, 0.1, 1.0, 2.5, 30.0, 1000.0])
def test_exif_exposure_time_and_iso(tmp_path, t):
    data = np.zeros((64, 64), np.uint16)
    fr = read_raw(_dng(tmp_path / "t.dng", data, t=t, iso=1600))
    num, den = exposure_rational(t)
    assert fr.exposure_time == float(Fraction(num, den))
    assert fr.exposure_time == pytest.approx(t, rel=1e-6)
    assert fr.iso == 1600
    # rawpy/LibRaw reads the same EXIF (it is what HDRMerge uses)
    import rawpy

    with rawpy.imread(str(tmp_path / "t.dng")) as raw:
        assert raw.other.shutter_speed == pytest.approx(t, rel=1e-6)
        assert raw.other.iso_speed == 1600


def test_explicit_exposure_time_overrides(tmp_path):
    fr = read_raw(_dng(tmp_path / "a.dng", np.ones((64, 64), np.uint16)), exposure_time=0.5)
    assert fr.exposure_time == 0.5


def test_png_and_tiff_frames_need_times(tmp_path):
    import tifffile
    from PIL import Image

    data = (np.arange(64, dtype=np.uint16) * 1000).reshape(8, 8)
    Image.fromarray(data).save(tmp_path / "a.png")
    tifffile.imwrite(tmp_path / "b.tif", data)
    for name in ("a.png", "b.tif"):
        fr = read_frame(tmp_path / name, 0.01)
        assert np.array_equal(fr.data, data) and fr.exposure_time == 0.01
        with pytest.raises(InputError, match="explicit exposure time"):
            read_frame(tmp_path / name)


def test_bad_inputs(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_frame(tmp_path / "missing.dng")
    (tmp_path / "notraw.dng").write_text("hello, I am not a raw file\n" * 10)
    with pytest.raises(InputError, match="notraw.dng"):
        read_frame(tmp_path / "notraw.dng")
    good = _dng(tmp_path / "good.dng", np.ones((64, 64), np.uint16))
    blob = good.read_bytes()
    (tmp_path / "trunc.dng").write_bytes(blob[: len(blob) // 2])
    with pytest.raises(InputError, match="trunc.dng"):
        read_frame(tmp_path / "trunc.dng")
    (tmp_path / "empty.dng").write_bytes(b"")
    with pytest.raises(InputError, match="empty"):
        read_frame(tmp_path / "empty.dng")
    with pytest.raises(InputError, match="exposure time"):
        read_frame(good, exposure_time=-1)


def test_check_frames_sizes_and_duplicates(tmp_path):
    a = read_raw(_dng(tmp_path / "a.dng", np.ones((64, 64), np.uint16)))
    b = read_raw(_dng(tmp_path / "b.dng", np.ones((64, 66), np.uint16)))
    c = read_raw(_dng(tmp_path / "c.dng", np.ones((64, 64), np.uint16)))
    with pytest.raises(InputError, match="differs"):
        check_frames([a, b])
    with pytest.raises(InputError, match="duplicate"):
        check_frames([a, c])
    with pytest.raises(InputError, match="twice"):
        check_frames([a, a])


def test_exr_round_trip_all_channels_and_attributes(tmp_path):
    rng = np.random.default_rng(2)
    ch = {
        "irradiance": rng.lognormal(5, 3, (20, 30)).astype(np.float32),
        "sigma": rng.random((20, 30)).astype(np.float32),
        "nexp": rng.integers(0, 7, (20, 30)).astype(np.float32),
    }
    attrs = {
        "unit": "electrons per second per photosite",
        "cfa_pattern": "RGGB",
        "exposure_times": [1 / 3, 0.001, 1000.0],
        "calibration": {"g": 0.23, "name": "x"},
        "hdrcap_version": "0.1.0",
        "merge": {"iterations": 3, "saturation": "threshold"},
    }
    path = write_exr(tmp_path / "o.exr", ch, attrs)
    back = read_exr(path)
    assert set(back.channels) == set(ch)
    for k in ch:
        assert back.channels[k].dtype == np.float32 and np.array_equal(back.channels[k], ch[k])
    assert back.header == json.loads(json.dumps(attrs))  # full float64 precision kept
    with pytest.raises(OutputExistsError):
        write_exr(path, ch, attrs)
    write_exr(path, {"irradiance": ch["sigma"]}, {}, force=True)
    assert set(read_exr(path).channels) == {"irradiance"}


def test_atomic_output_leaves_nothing_on_error(tmp_path):
    target = tmp_path / "x.txt"
    with pytest.raises(RuntimeError), atomic_output(target) as tmp:
        tmp.write_text("partial")
        raise RuntimeError("boom")
    assert not target.exists() and list(tmp_path.iterdir()) == []
    with pytest.raises(InputError, match="does not exist"):
        with atomic_output(tmp_path / "nofolder" / "x.txt"):
            pass


def test_atomic_output_gets_the_usual_file_mode(tmp_path):
    """Outputs are readable like any file the process creates (mkstemp alone gives 0600)."""
    import stat

    from hdrcap.pipeline.io import files as pio

    target = tmp_path / "out.txt"
    with atomic_output(target) as tmp:
        tmp.write_text("x")
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~pio._UMASK


def test_emva_descriptor(emva_dir):
    ds = read_emva_descriptor(emva_dir / "EMVA1288_Data.txt")
    assert (ds.bits, ds.width, ds.height) == (12, 640, 480)
    assert len(ds.bright()) == 51 and len(ds.dark()) == 51
    first = ds.bright()[0]
    assert first.exposure_time == pytest.approx(40e-6) and first.photons == 120.0
    assert all(p.is_file() for s in ds.steps for p in s.images)  # Windows separators handled
    assert sum(len(s.images) for s in ds.steps) == 300
    fr = read_frame(first.images[0], first.exposure_time)
    assert fr.shape == (480, 640) and fr.data.max() < 4096


def test_emva_descriptor_errors(tmp_path):
    p = tmp_path / "d.txt"
    p.write_text("v 3.0\nb 100 1\ni a.png\nx nonsense\n")
    with pytest.raises(InputError, match=r"d.txt:4"):
        read_emva_descriptor(p)


def test_check_frames_bracket_passes_and_sampled_twins_are_not_duplicates(tmp_path):
    from hdrcap.mock_camera import PRESETS
    from hdrcap.mock_camera.backend import SimulatedCamera
    from hdrcap.mock_camera.scenes import make_scene

    cam = SimulatedCamera(PRESETS["camera-A"], make_scene("hdr", (64, 96), 4.0, 2e5), seed=1)
    times = (1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4, 1.0)
    bracket = [read_raw(cam.capture_to(tmp_path / f"f{i}.dng", t)) for i, t in enumerate(times)]
    darks = [read_raw(cam.capture_to(tmp_path / f"d{i}.dng", t, dark=True)) for i, t in enumerate(times)]
    assert len(check_frames(bracket)) == 6 and len(check_frames(darks, "dark frame")) == 6
    # identical in every sampled row, different in one photosite elsewhere: not a duplicate
    a = np.zeros((64, 64), np.uint16)
    b = a.copy()
    b[1, 1] = 1
    c = a.copy()
    fa, fb, fc = (read_raw(_dng(tmp_path / f"{n}.dng", x)) for n, x in (("a", a), ("b", b), ("c", c)))
    assert len(check_frames([fa, fb])) == 2
    with pytest.raises(InputError, match="c.dng: duplicate frame, its pixels are identical to .*a.dng"):
        check_frames([fa, fb, fc])


def test_check_frames_catches_a_copy_with_another_exposure_time(tmp_path):
    data = np.random.default_rng(3).integers(0, 4096, (64, 64), dtype=np.uint16)
    a = read_raw(_dng(tmp_path / "a.dng", data, t=1 / 250))
    b = read_raw(_dng(tmp_path / "b.dng", data, t=1 / 60))
    with pytest.raises(InputError, match="b.dng: duplicate frame"):
        check_frames([a, b])


def _merge_like_channels(shape=(20, 30)):
    rng = np.random.default_rng(4)
    irr = rng.lognormal(5, 3, shape).astype(np.float32)
    return {
        "irradiance": irr,
        "sigma": (np.sqrt(irr) + 15).astype(np.float32),
        "nexp": rng.integers(0, 7, shape).astype(np.float32),
    }


@pytest.mark.parametrize("compression", ["zip", "zips", "piz", "zstd", "rle", "none"])
def test_exr_half_sigma_and_uint_nexp_read_back_as_float32(tmp_path, compression):
    from hdrcap.pipeline.io.exr import HALF_RELATIVE_ERROR

    ch = _merge_like_channels()
    path = write_exr(
        tmp_path / "o.exr",
        ch,
        {"unit": "e-/s"},
        compression=compression,
        precision={"sigma": "half", "nexp": "uint"},
        threads=2,
    )
    back = read_exr(path)
    assert all(back.channels[k].dtype == np.float32 for k in ch)
    assert np.array_equal(back.channels["irradiance"], ch["irradiance"])
    assert np.array_equal(back.channels["nexp"], ch["nexp"])
    rel = np.abs(back.channels["sigma"] / ch["sigma"] - 1)
    assert 0 < rel.max() <= HALF_RELATIVE_ERROR
    import OpenEXR

    with OpenEXR.File(str(path)) as exr:
        types = {name: str(c.type()) for name, c in exr.channels().items()}
    assert types == {"irradiance": "PixelType.FLOAT", "sigma": "PixelType.HALF", "nexp": "PixelType.UINT"}
    assert OpenEXR.global_thread_count() == 2


def test_exr_native_read_and_same_type_write_keep_every_bit(tmp_path):
    """read_exr(native=True) gives the stored types (float32, float16, uint32) with the values
    of the float32 read; writing them back stores each as it is, bit for bit, including
    subnormal halves (already half: nothing to lose, so not refused as float32 input is)."""
    import OpenEXR

    ch = _merge_like_channels()
    sigma = ch["sigma"].astype(np.float16)
    sigma[0, :3] = np.array([6e-8, 3e-6, -2e-5], np.float16)  # subnormal halves
    image = ExrContent(dict(ch, sigma=sigma), {"unit": "e-/s"})
    path = write_exr(tmp_path / "a.exr", *image, precision={"sigma": "half", "nexp": "uint"})
    native = read_exr(path, native=True)
    plain = read_exr(path)
    assert {k: v.dtype for k, v in native.channels.items()} == {
        "irradiance": np.float32,
        "sigma": np.float16,
        "nexp": np.uint32,
    }
    for k in ch:
        assert np.array_equal(native.channels[k].astype(np.float32), plain.channels[k]), k
    assert native.channels["sigma"].tobytes() == sigma.tobytes()
    for prec in ("half", "auto"):
        again = write_exr(tmp_path / f"b-{prec}.exr", *native, precision={"sigma": prec, "nexp": "uint"})
        back = read_exr(again, native=True)
        for k in ch:
            assert back.channels[k].tobytes() == native.channels[k].tobytes(), (prec, k)
        with OpenEXR.File(str(again)) as exr:
            assert str(exr.channels()["sigma"].type()) == "PixelType.HALF"
    with pytest.raises(ValueError, match="outside the half range"):  # the same values as float32
        write_exr(tmp_path / "c.exr", dict(ch, sigma=sigma.astype(np.float32)), {}, precision={"sigma": "half"})


def test_exr_precision_refuses_what_it_would_lose(tmp_path):
    ch = _merge_like_channels()
    image = ExrContent(ch, {})
    with pytest.raises(ValueError, match="irradiance channel is always stored as float"):
        write_exr(tmp_path / "a.exr", *image, precision={"irradiance": "half"})
    big = ExrContent(dict(ch, sigma=np.full((20, 30), 1e5, np.float32)), {})
    with pytest.raises(ValueError, match="'sigma': values .* outside the half range"):
        write_exr(tmp_path / "b.exr", *big, precision={"sigma": "half"})
    frac = ExrContent(dict(ch, nexp=np.full((20, 30), 0.5, np.float32)), {})
    with pytest.raises(ValueError, match="'nexp': uint needs whole numbers"):
        write_exr(tmp_path / "c.exr", *frac, precision={"nexp": "uint"})
    with pytest.raises(ValueError, match="precision given for channels the image does not have: x"):
        write_exr(tmp_path / "d.exr", *image, precision={"x": "half"})
    with pytest.raises(ValueError, match="precision must be one of"):
        write_exr(tmp_path / "e.exr", *image, precision={"sigma": "double"})
    # infinities and zeros are stored exactly as half
    special = ExrContent(dict(ch, sigma=np.where(ch["nexp"] == 0, np.inf, 0).astype(np.float32)), {})
    back = read_exr(write_exr(tmp_path / "f.exr", *special, precision={"sigma": "half"}))
    assert np.array_equal(back.channels["sigma"], special.channels["sigma"])
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())


def test_exr_auto_precision_is_half_only_where_it_fits(tmp_path):
    import OpenEXR

    ch = _merge_like_channels()
    for sigma, expect in ((ch["sigma"], "PixelType.HALF"), (ch["sigma"] * 1e4, "PixelType.FLOAT")):
        path = write_exr(tmp_path / f"{expect}.exr", dict(ch, sigma=sigma), precision={"sigma": "auto"})
        with OpenEXR.File(str(path)) as exr:
            assert str(exr.channels()["sigma"].type()) == expect


def test_exr_layout_survives_corrupt_files(tmp_path):
    """Random byte changes to an EXR never crash the layout reader (an error, not a signal):
    OpenEXR's old InputFile binding crashed on some of these."""
    import subprocess
    import sys

    ch = {"irradiance": np.arange(64 * 48, dtype=np.float32).reshape(48, 64), "sigma": np.ones((48, 64), np.float32)}
    good = write_exr(tmp_path / "good.exr", ch, {"unit": "e-/s"})
    raw = bytearray(good.read_bytes())
    rng = np.random.default_rng(5)
    paths = []
    for k in range(40):
        data = bytearray(raw)
        for pos in rng.integers(0, 400, size=3):  # the header and the offset table
            data[pos] = int(rng.integers(0, 256))
        (tmp_path / f"{k}.exr").write_bytes(bytes(data))
        paths.append(str(tmp_path / f"{k}.exr"))
    code = (
        "import sys\nfrom hdrcap.pipeline.errors import InputError\nfrom hdrcap.pipeline.io.exr import read_exr_layout\n"
        "for p in sys.argv[1:]:\n    try:\n        read_exr_layout(p)\n    except InputError:\n        pass\nprint('ok')"
    )
    proc = subprocess.run([sys.executable, "-c", code, *paths], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stderr[-500:]
