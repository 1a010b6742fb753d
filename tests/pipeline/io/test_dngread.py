"""Direct DNG decoding against LibRaw: the same pixels, levels and CFA pattern for every file the
simulator writes and for uncompressed variants (strips, tiles, byte orders, 8 bits, active
area); LibRaw for the rest; one-line errors for inconsistent files."""

import struct

import numpy as np
import pytest
import tifffile

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io import raw as pio
from hdrcap.pipeline.io.dngread import decode_dng
from tests.helpers.dng import write_test_dng


def _tiff_dng(path, data, *, cfa=(0, 1, 1, 2), black=128, white=4095, active=None, **kw):
    """An uncompressed DNG written by tifffile, in the layouts the simulator does not use."""
    tags = [
        (50706, "B", 4, (1, 4, 0, 0), True),
        (271, "s", 0, "Acme", True),
        (272, "s", 0, "Sim 1", True),
        (33421, "H", 2, (2, 2), True),
        (33422, "B", 4, cfa, True),
        (50710, "B", 3, (0, 1, 2), True),
        (50714, "I", 1, black, True),
        (50717, "I", 1, white, True),
        (50708, "s", 0, "Acme Sim 1", True),
        (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1), True),
        (33434, "2I", 1, (1, 250), True),
        (34855, "H", 1, 400, True),
        (36867, "s", 0, "2026:01:02 03:04:05", True),
    ]
    if active is not None:
        tags.append((50829, "I", 4, active, True))
    tifffile.imwrite(path, data, photometric=32803, extratags=tags, metadata=None, subfiletype=0, **kw)
    return path


def _decoded_directly(path) -> bool:
    with tifffile.TiffFile(path) as tif:
        return decode_dng(path, tif) is not None


def _assert_same_as_libraw(path, direct=True):
    fr = pio.read_raw(path)
    ref = pio._libraw_decode(path)  # private on purpose: LibRaw's decoding is the reference
    assert _decoded_directly(path) is direct
    assert fr.data.dtype == np.uint16 and fr.data.shape == ref.data.shape
    assert np.array_equal(fr.data, ref.data)
    assert (fr.black_level, fr.white_level, fr.cfa_pattern) == (ref.black, ref.white, ref.cfa)
    return fr


@pytest.mark.parametrize("cfa", ["RGGB", "BGGR", "GRBG", "GBRG"])
@pytest.mark.parametrize("shape", [(22, 22), (23, 37), (101, 77), (480, 640)])
def test_simulator_dng_identical_to_libraw(tmp_path, cfa, shape):
    rng = np.random.default_rng(shape[0])
    for bits in range(8, 17):
        white = (1 << bits) - 1
        data = rng.integers(0, white + 1, shape, dtype=np.uint16)
        data.flat[:2] = (0, white)  # the extremes
        fr = _assert_same_as_libraw(
            write_test_dng(tmp_path / f"{bits}.dng", data, cfa=cfa, black=0.37 * white, white=white)
        )
        assert np.array_equal(fr.data, data) and fr.cfa_pattern == cfa


@pytest.mark.parametrize("preset", ["camera-A", "camera-B"])
def test_simulated_camera_files_identical_to_libraw(tmp_path, preset):
    from hdrcap.mock_camera import PRESETS
    from hdrcap.mock_camera.backend import SimulatedCamera
    from hdrcap.mock_camera.scenes import make_scene

    cam = SimulatedCamera(PRESETS[preset], make_scene("hdr", (64, 96), 4.0, 2e5), seed=3)
    for i, t in enumerate((1 / 1000, 1 / 15, 1.0)):
        fr = _assert_same_as_libraw(cam.capture_to(tmp_path / f"f{i}.dng", t))
        assert fr.exposure_time == pytest.approx(t, rel=1e-6)
    _assert_same_as_libraw(cam.capture_to(tmp_path / "d.dng", 0.1, dark=True))


@pytest.mark.parametrize(
    "layout",
    [
        {"byteorder": ">"},
        {"rowsperstrip": 7},
        {"tile": (32, 48)},
        {"tile": (64, 64), "byteorder": ">"},
        {"dtype": np.uint8, "white": 255},
        {"dtype": np.uint8, "tile": (32, 32), "white": 255},
        {"active": (2, 4, 98, 146)},
        {"cfa": (1, 0, 2, 1)},
    ],
)
def test_uncompressed_layouts_identical_to_libraw(tmp_path, layout):
    layout = dict(layout)
    dtype = layout.pop("dtype", np.uint16)
    data = np.random.default_rng(5).integers(0, layout.get("white", 4095) + 1, (100, 150), dtype=dtype)
    _assert_same_as_libraw(_tiff_dng(tmp_path / "v.dng", data, **layout))


@pytest.mark.parametrize("layout", [{"active": (1, 0, 99, 150)}, {"active": (1, 1, 99, 149)}, {"cfa": (0, 1, 2, 1)}])
def test_what_libraw_reads_differently_goes_to_libraw(tmp_path, layout):
    data = np.random.default_rng(6).integers(0, 4096, (100, 150), dtype=np.uint16)
    _assert_same_as_libraw(_tiff_dng(tmp_path / "v.dng", data, **layout), direct=False)


def test_compressed_dng_is_left_to_libraw(tmp_path):
    data = np.random.default_rng(7).integers(0, 4096, (64, 64), dtype=np.uint16)
    path = _tiff_dng(tmp_path / "z.dng", data, compression="zlib")
    assert not _decoded_directly(path)
    with pytest.raises(InputError, match="z.dng"):  # LibRaw reads no integer deflate DNG either
        pio.read_raw(path)


def test_missing_metadata_falls_back_to_libraw(tmp_path):
    """Without DateTimeOriginal the timestamp is LibRaw's, as before."""
    data = np.random.default_rng(8).integers(0, 4096, (64, 64), dtype=np.uint16)
    tags = [
        (50706, "B", 4, (1, 4, 0, 0), True),
        (33421, "H", 2, (2, 2), True),
        (33422, "B", 4, (0, 1, 1, 2), True),
        (50717, "I", 1, 4095, True),
        (50708, "s", 0, "Acme Sim 1", True),
        (33434, "2I", 1, (1, 250), True),
        (34855, "H", 1, 400, True),
    ]
    path = tmp_path / "m.dng"
    tifffile.imwrite(path, data, photometric=32803, extratags=tags, metadata=None, subfiletype=0)
    fr = pio.read_raw(path)
    assert np.array_equal(fr.data, data) and fr.exposure_time == 1 / 250


def test_mapped_frame_is_private(tmp_path):
    data = np.arange(64 * 64, dtype=np.uint16).reshape(64, 64)
    path = write_test_dng(tmp_path / "a.dng", data)
    blob = path.read_bytes()
    fr = pio.read_raw(path)
    fr.data[0, 0] = 7  # copy-on-write: the file is unchanged
    assert path.read_bytes() == blob
    assert isinstance(pio.read_raw(path, mmap=False).data, np.ndarray)
    assert np.array_equal(pio.read_raw(path, mmap=False).data, data)


def _patch_tag(blob: bytes, tag: int, value: int) -> bytes:
    """Set the (first) LONG value of ``tag`` in IFD0 of a little-endian TIFF."""
    ifd = struct.unpack_from("<I", blob, 4)[0]
    n = struct.unpack_from("<H", blob, ifd)[0]
    for i in range(n):
        pos = ifd + 2 + 12 * i
        if struct.unpack_from("<H", blob, pos)[0] == tag:
            return blob[: pos + 8] + struct.pack("<I", value) + blob[pos + 12 :]
    raise KeyError(tag)


def test_inconsistent_files_are_refused(tmp_path):
    data = np.ones((64, 64), np.uint16)
    blob = write_test_dng(tmp_path / "a.dng", data).read_bytes()
    (tmp_path / "short.dng").write_bytes(_patch_tag(blob, 279, 64 * 64))  # half the bytes 64x64x16 bit needs
    with pytest.raises(InputError, match=r"short.dng: raw image data does not match its dimensions \(64x64"):
        pio.read_raw(tmp_path / "short.dng")
    (tmp_path / "beyond.dng").write_bytes(_patch_tag(blob, 279, 64 * 64 * 2 + 10))
    with pytest.raises(InputError, match="beyond.dng: truncated raw file"):
        pio.read_raw(tmp_path / "beyond.dng")
    (tmp_path / "tall.dng").write_bytes(_patch_tag(blob, 257, 65))  # one row more than the data
    with pytest.raises(InputError, match="tall.dng: raw image data does not match"):
        pio.read_raw(tmp_path / "tall.dng")
