"""The zarr format 2 files of the run archive that hdrcap writes itself: array metadata
(``.zarray``), chunk encoding, consolidated metadata (``.zmetadata``), atomic file writes.

The format is zarr's version 2 storage specification
(https://zarr-specs.readthedocs.io/en/latest/v2/v2.0.html), which zarr-python 2 and 3, xarray
and other zarr readers read. The batch writes these files directly rather than through
zarr-python so that a worker can write a run's chunk files with numcodecs alone and the client
can commit runs by rewriting a few small JSON files (no zarr or xarray on either path, nothing
proportional to the pixels on the client). Every array of the archive uses the one layout of
:func:`array_metadata`: C order, chunk files named ``I.0.0`` (``.`` separator), Blosc LZ4, which
is what xarray wrote for the archive before; :func:`encode_chunk` gives the bytes zarr-python
writes for the same chunk (tests/test_archive.py checks both directions).
"""

from __future__ import annotations

import functools
import json
import os
import secrets
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "COMPRESSOR",
    "array_metadata",
    "chunk_name",
    "chunk_index",
    "encode_chunk",
    "decode_chunk",
    "write_atomic",
    "write_json",
    "read_json",
]

#: The compressor of every chunk (numcodecs configuration).
COMPRESSOR: dict[str, Any] = {"id": "blosc", "cname": "lz4", "clevel": 5, "shuffle": 1, "blocksize": 0}
#: Filters of string arrays (variable-length UTF-8).
_STRING_FILTERS = [{"id": "vlen-utf8"}]


def array_metadata(shape: Sequence[int], dtype: str) -> dict[str, Any]:
    """The ``.zarray`` of an archive array: one chunk per index of the first dimension.

    Parameters
    ----------
    shape : sequence of int
        Array shape; the first dimension is ``run``.
    dtype : {"<f4", "<i8", "|O"}
        float32, int64, or UTF-8 strings.

    Returns
    -------
    dict
        The metadata as zarr format 2 stores it.
    """
    if dtype not in ("<f4", "<i8", "|O"):
        raise ValueError(f"unsupported archive dtype {dtype!r}")
    return {
        "shape": list(shape),
        "chunks": [1, *shape[1:]],
        "dtype": dtype,
        "fill_value": "NaN" if dtype == "<f4" else None,
        "order": "C",
        "filters": list(_STRING_FILTERS) if dtype == "|O" else None,
        "dimension_separator": ".",
        "compressor": dict(COMPRESSOR),
        "zarr_format": 2,
    }


def chunk_name(index: int, ndim: int) -> str:
    """The file name of the chunk of run ``index`` in an array of ``ndim`` dimensions."""
    return ".".join([str(index)] + ["0"] * (ndim - 1))


def chunk_index(name: str) -> int | None:
    """The run index of the chunk file ``name`` (None: not a chunk file)."""
    head = name.split(".", 1)[0]
    return int(head) if head.isdigit() else None


@functools.lru_cache(maxsize=8)
def _codec(config: str) -> Any:
    import numcodecs

    return numcodecs.get_codec(json.loads(config))


def _codecs(meta: dict[str, Any]) -> tuple[list[Any], Any]:
    filters = [_codec(json.dumps(f, sort_keys=True)) for f in meta.get("filters") or []]
    comp = meta.get("compressor")
    return filters, None if comp is None else _codec(json.dumps(comp, sort_keys=True))


def encode_chunk(meta: dict[str, Any], values: Any) -> bytes:
    """One chunk encoded as ``meta`` says (the bytes zarr-python writes for it).

    Parameters
    ----------
    meta : dict
        The array's ``.zarray``.
    values : array_like
        The chunk's values, of the chunk's shape (a run: ``(1, H, W)`` or ``(1,)``).

    Returns
    -------
    bytes
    """
    arr = np.ascontiguousarray(np.asarray(values, dtype=object if meta["dtype"] == "|O" else meta["dtype"]))
    if tuple(arr.shape) != tuple(meta["chunks"]):
        arr = arr.reshape(meta["chunks"])
    filters, comp = _codecs(meta)
    buf: Any = arr
    for f in filters:
        buf = f.encode(buf)
    return bytes(comp.encode(buf) if comp is not None else np.asarray(buf).tobytes())


def decode_chunk(meta: dict[str, Any], data: bytes) -> np.ndarray:
    """The values of a chunk file (:func:`encode_chunk` reversed).

    Parameters
    ----------
    meta : dict
        The array's ``.zarray``.
    data : bytes
        The chunk file's content.

    Returns
    -------
    numpy.ndarray
        Of the chunk's shape.
    """
    filters, comp = _codecs(meta)
    buf: Any = comp.decode(data) if comp is not None else data
    for f in reversed(filters):
        buf = f.decode(buf)
    if meta["dtype"] == "|O":
        return np.asarray(buf, dtype=object).reshape(meta["chunks"])
    return np.frombuffer(buf, dtype=meta["dtype"]).reshape(meta["chunks"])


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``path`` whole or not at all (a temporary file beside it, then a rename): a reader
    sees the old file or the new one, never part of one.

    Parameters
    ----------
    path : Path
        The file.
    data : bytes
        Its content.
    """
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(6)}.partial")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_json(path: Path, obj: Any) -> None:
    """:func:`write_atomic` of ``obj`` as JSON."""
    write_atomic(path, json.dumps(obj, allow_nan=False).encode())


def read_json(path: Path) -> Any:
    """The JSON file ``path`` (None if it does not exist)."""
    try:
        return json.loads(path.read_bytes())
    except FileNotFoundError:
        return None
