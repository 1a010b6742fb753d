"""write_exr writes block by block without full-size copies, and its files are byte for byte
those of OpenEXR's own whole-image writer given the channels converted in one piece."""

import hashlib
import tracemalloc

import numpy as np
import pytest

from hdrcap.pipeline.io.exr import EXR_PRECISIONS, write_exr
from hdrcap.pipeline.io.results import write_result
from hdrcap.pipeline.result import HdrResult


def _channels(shape=(301, 257), seed=4):
    rng = np.random.default_rng(seed)
    irr = rng.lognormal(3, 3, shape).astype(np.float32)
    irr[0, :4] = [np.nan, np.inf, -5.0, 0.0]
    sigma = rng.uniform(0.5, 3000, shape).astype(np.float32)
    sigma[1, :2] = [0.0, np.nan]
    return {
        "irradiance": irr,
        "sigma": sigma,
        "nexp": rng.integers(0, 7, shape).astype(np.float32),
        "quality": rng.integers(0, 64, shape).astype(np.uint8),
    }


def _whole_image_reference(path, channels, stored, header_attrs, compression):
    """The file OpenEXR.File writes from the channels converted in one piece."""
    import OpenEXR

    chans = {n: np.ascontiguousarray(a, dtype=EXR_PRECISIONS[stored[n]]) for n, a in channels.items()}
    head = {"compression": getattr(OpenEXR, compression), "type": OpenEXR.scanlineimage, **header_attrs}
    with OpenEXR.File(head, chans) as exr:
        exr.write(str(path))
    return path


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.parametrize(("compression", "code"), [("zip", "ZIP_COMPRESSION"), ("zstd", "ZSTD_COMPRESSION")])
@pytest.mark.parametrize("block_rows", [None, 7, 1000])
def test_blocks_give_the_bytes_of_the_whole_image_writer(tmp_path, compression, code, block_rows):
    ch = _channels()
    precision = {"sigma": "auto", "nexp": "uint", "quality": "uint"}
    got = write_exr(
        tmp_path / "blocks.exr",
        ch,
        {"unit": "e-/s"},
        compression=compression,
        precision=precision,
        block_rows=block_rows,
    )
    attrs = {"hdrcap": '{"unit": "e-/s"}', "hdrcap:unit": "e-/s"}
    stored = {"irradiance": "float", "sigma": "half", "nexp": "uint", "quality": "uint"}
    ref = _whole_image_reference(tmp_path / "ref.exr", ch, stored, attrs, code)
    assert _sha(got) == _sha(ref)


def test_memory_mapped_channels_give_the_same_file_as_arrays(tmp_path):
    ch = _channels()
    mapped = {}
    for name, arr in ch.items():
        np.save(tmp_path / f"{name}.npy", arr)
        mapped[name] = np.load(tmp_path / f"{name}.npy", mmap_mode="r")
    res = HdrResult(ch["irradiance"], ch["sigma"], ch["nexp"], quality=ch["quality"], header={"unit": "e-/s"})
    a = write_result(res, tmp_path / "a.exr")
    b = write_result(res.replace(**mapped), tmp_path / "b.exr")
    assert _sha(a) == _sha(b)


def test_no_full_size_copy_of_a_converted_channel(tmp_path):
    """Converting half / uint channels takes buffers of one block, not copies of the channels."""
    ch = _channels(shape=(4000, 500))  # one uint32 channel: 8 MB
    res = HdrResult(ch["irradiance"], ch["sigma"], ch["nexp"], quality=ch["quality"], header={"unit": "e-/s"})
    tracemalloc.start()
    try:
        write_result(res, tmp_path / "o.exr")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 4e6, f"peak {peak / 1e6:.1f} MB traced while writing"
