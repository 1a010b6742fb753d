"""Sanity checks on decoded raw data: a corrupt simulator DNG is refused with one line naming the
file and the problem, whether it is decoded directly (tifffile) or by LibRaw; frames whose
metadata contradicts the rest of their set are refused by check_frames."""

import contextlib
import io
import struct
from pathlib import Path

import pytest

from hdrcap.mock_camera import PRESETS
from hdrcap.mock_camera.backend import SimulatedCamera
from hdrcap.mock_camera.scenes import make_scene
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io import dngread
from hdrcap.pipeline.io import raw as pio

T = 1 / 100


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Two frames and a dark frame of the 10-bit simulated camera-B (64x48)."""
    folder = tmp_path_factory.mktemp("sanity")
    cam = SimulatedCamera(PRESETS["camera-B"], make_scene("hdr", (48, 64), 3.0, 2e5), seed=5)
    return [cam.capture_to(folder / "a.dng", T), cam.capture_to(folder / "b.dng", 10 * T)]


@pytest.fixture(params=["direct", "libraw"])
def decoder(request, monkeypatch):
    """Read through the direct DNG decoder, or force LibRaw; gives the files LibRaw decoded."""
    calls = []
    libraw = pio._libraw_decode
    monkeypatch.setattr(pio, "_libraw_decode", lambda path: calls.append(path) or libraw(path))
    if request.param == "libraw":
        monkeypatch.setattr(dngread, "decode_dng", lambda *a, **k: None)
    return calls


def _entry(blob: bytes, tag: int) -> int:
    """Byte offset of the IFD0 entry of ``tag`` in a little-endian TIFF."""
    ifd = struct.unpack_from("<I", blob, 4)[0]
    for i in range(struct.unpack_from("<H", blob, ifd)[0]):
        pos = ifd + 2 + 12 * i
        if struct.unpack_from("<H", blob, pos)[0] == tag:
            return pos
    raise KeyError(tag)


def _value_offset(blob: bytes, tag: int) -> int:
    """Where the value of ``tag`` (stored outside its IFD entry) starts."""
    return struct.unpack_from("<I", blob, _entry(blob, tag) + 8)[0]


def _flip4(blob: bytes, offset: int) -> bytes:
    out = bytearray(blob)
    out[offset : offset + 4] = bytes(b ^ 0xFF for b in out[offset : offset + 4])
    return bytes(out)


def _put(blob: bytes, offset: int, fmt: str, *values) -> bytes:
    out = bytearray(blob)
    struct.pack_into(fmt, out, offset, *values)
    return bytes(out)


def _write(tmp_path: Path, name: str, blob: bytes) -> Path:
    path = tmp_path / name
    path.write_bytes(blob)
    return path


def test_intact_frames_are_read_by_both_decoders(frames, decoder, request):
    fr = pio.read_raw(frames[0])
    assert decoder == ([frames[0]] if request.node.callspec.params["decoder"] == "libraw" else [])
    assert (fr.white_level, fr.black_level, fr.cfa_pattern) == (1023, 32, "RGGB")
    assert fr.exposure_time == pytest.approx(T, rel=1e-6)


def test_four_bytes_flipped_at_offset_100_are_refused(frames, decoder, tmp_path):
    """The issue's reproduction: four bytes flipped at offset 100 (an IFD0 entry) were merged silently."""
    bad = _write(tmp_path, "flipped.dng", _flip4(frames[0].read_bytes(), 100))
    with pytest.raises(InputError, match=r"flipped.dng: corrupt DNG directory: IFD entry at byte \d+") as err:
        pio.read_raw(bad)
    assert "\n" not in str(err.value)


def test_broken_strip_offset_is_refused(frames, decoder, tmp_path):
    blob = frames[0].read_bytes()
    bad = _write(tmp_path, "strip.dng", _flip4(blob, _entry(blob, 273) + 8))
    with pytest.raises(InputError, match="strip.dng: (corrupt DNG directory|truncated raw file)"):
        pio.read_raw(bad)


def test_values_above_the_white_level_are_refused(frames, decoder, tmp_path):
    """65535 in a 10-bit file (what LibRaw returned from a corrupt file) is no sensor value."""
    blob = frames[0].read_bytes()
    data = _value_offset(blob, 273)  # StripOffsets: one strip, the value is its offset
    bad = _write(tmp_path, "hot.dng", _put(blob, data + 2 * 100, "<HH", 65535, 1024))
    with pytest.raises(InputError, match=r"hot.dng: 2 photosites above the white level \(65535 DN > 1023 DN"):
        pio.read_raw(bad)
    assert pio.read_raw(_write(tmp_path, "top.dng", _put(blob, data, "<H", 1023))).data[0, 0] == 1023


@pytest.mark.parametrize("white, top", [(255, 255), (1023, 1023), (4095, 4095), (15000, 16383), (65535, 65535)])
def test_adc_maximum_is_the_white_levels_bit_range(white, top):
    assert pio.adc_maximum(white) == top


def test_black_level_above_the_white_level_is_refused(frames, decoder, tmp_path):
    blob = frames[0].read_bytes()
    bad = _write(tmp_path, "black.dng", _put(blob, _value_offset(blob, 50714), "<II", 2000, 1))
    with pytest.raises(InputError, match=r"black.dng: black level 2000.0 DN is not between 0 and the white level 1023"):
        pio.read_raw(bad)


def test_exposure_time_zero_is_refused(frames, decoder, tmp_path):
    blob = frames[0].read_bytes()
    ifd0 = _value_offset(blob, 33434)
    exif = blob.index(blob[ifd0 : ifd0 + 8], _value_offset(blob, 34665))  # the same rational in the EXIF IFD
    assert exif != ifd0
    zero_in_ifd0 = _write(tmp_path, "t0.dng", _put(blob, ifd0, "<II", 0, 1))
    with pytest.raises(InputError, match=r"t0.dng: the metadata contradicts itself: ExposureTime 0.0 s in IFD0"):
        pio.read_raw(zero_in_ifd0)
    zero_in_both = _write(tmp_path, "t00.dng", _put(_put(blob, ifd0, "<II", 0, 1), exif, "<II", 0, 1))
    with pytest.raises(InputError, match="t00.dng: exposure time must be a positive number of seconds, got 0.0"):
        pio.read_raw(zero_in_both)


def test_zero_width_is_refused(frames, decoder, tmp_path):
    blob = frames[0].read_bytes()
    bad = _write(tmp_path, "w0.dng", _put(blob, _entry(blob, 256) + 8, "<I", 0))
    with pytest.raises(InputError, match="w0.dng: "):
        pio.read_raw(bad)


def test_frames_contradicting_their_set_are_refused(frames, tmp_path):
    a, b = pio.read_raw(frames[0]), pio.read_raw(frames[1])
    pio.check_frames([a, b])
    blob = frames[1].read_bytes()
    no_black = _write(tmp_path, "noblack.dng", _put(blob, _value_offset(blob, 50714), "<II", 0, 1))
    with pytest.raises(InputError, match=r"noblack.dng: black level 0 DN differs from .*a.dng \(32 DN\)"):
        pio.check_frames([a, pio.read_raw(no_black)])
    white = _write(tmp_path, "white.dng", _put(blob, _entry(blob, 50717) + 8, "<I", 4095))
    with pytest.raises(InputError, match=r"white.dng: white level 4095 DN differs from .*a.dng \(1023 DN\)"):
        pio.check_frames([a, pio.read_raw(white)])
    mono = pio.RawFrame(
        data=b.data,
        exposure_time=b.exposure_time,
        black_level=b.black_level,
        white_level=b.white_level,
        cfa_pattern=None,
        path="mono.dng",
    )
    with pytest.raises(InputError, match=r"mono.dng: CFA pattern None differs from .*a.dng \(RGGB\)"):
        pio.check_frames([a, mono])


def test_the_corrupt_dng_is_refused_by_the_merge_command(frames, tmp_path):
    from hdrcap.cli import main

    bad = _write(tmp_path, "flipped.dng", _flip4(frames[0].read_bytes(), 100))
    out = tmp_path / "out.exr"
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc = main(["merge", str(bad), str(frames[1]), "--camera", "camera-B", "-o", str(out)])
    assert rc == 2 and not out.exists()
    assert err.getvalue().count("\n") == 1 and err.getvalue().startswith(f"hdrcap: error: {bad}: corrupt DNG")


def test_dimensions_the_data_cannot_hold_are_refused_before_decoding(frames, decoder, tmp_path):
    """30000x30000 compressed photosites in 6 kB: LibRaw allocated 1.7 GB and returned zeros."""
    blob = frames[0].read_bytes()
    for tag, value in ((256, 30000), (257, 30000), (278, 30000), (259, 7)):
        blob = _put(blob, _entry(blob, tag) + 8, "<I", value)
    with pytest.raises(InputError, match=r"big.dng: impossible raw image dimensions 30000x30000 \(16-bit\)"):
        pio.read_raw(_write(tmp_path, "big.dng", blob))
