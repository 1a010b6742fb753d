"""Files at the edge: atomic, no-clobber writes, readable-file checks, hashes, and releasing the
pages of memory-mapped inputs."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import tempfile
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from hdrcap.pipeline.errors import InputError, OutputExistsError

__all__ = [
    "NO_HARD_LINKS",
    "atomic_output",
    "check_new_output",
    "check_readable",
    "one_line",
    "place_new",
    "quiet_stderr",
    "release_mapped_pages",
    "sha256_file",
]


def check_readable(path: Path) -> None:
    """Refuse an input file that is missing, a folder or empty, with a one-line error.

    Parameters
    ----------
    path : pathlib.Path
        The file.

    Raises
    ------
    InputError
        Naming the file and what is wrong.
    """
    if not path.exists():
        raise InputError(f"{path}: no such file")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a frame")
    if path.stat().st_size == 0:
        raise InputError(f"{path}: empty file")


def check_new_output(path: str | os.PathLike[str], force: bool = False) -> Path:
    """Refuse an output that exists before any work is done (:func:`atomic_output` checks
    again when it writes).

    Parameters
    ----------
    path : str or os.PathLike
        The output file or folder.
    force : bool
        An existing output may be replaced.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    OutputExistsError
        ``path`` exists and ``force`` is false.
    """
    path = Path(path)
    if path.exists() and not force:
        raise OutputExistsError(f"{path}: exists; use --force to overwrite")
    return path


def one_line(err: BaseException, limit: int = 200) -> str:
    """``Type: message`` of an exception on one line.

    Parameters
    ----------
    err : BaseException
        The exception.
    limit : int
        Most characters kept (longer text ends in ``...``).

    Returns
    -------
    str
    """
    text = " ".join(f"{type(err).__name__}: {err}".split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


_STDERR_LOCK = threading.Lock()


@contextlib.contextmanager
def quiet_stderr() -> Iterator[None]:
    """Silence C libraries' own messages on file descriptor 2 (LibRaw, OpenEXR: our one-line
    error says it all), for the duration of a ``with`` block; one thread at a time.

    Returns
    -------
    contextlib.AbstractContextManager
        The ``with`` block's context.
    """
    with _STDERR_LOCK:
        try:
            saved = os.dup(2)
        except OSError:  # no stderr at all
            yield
            return
        try:
            with open(os.devnull, "wb") as null:
                os.dup2(null.fileno(), 2)
                yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def release_mapped_pages(arrays: Iterable[np.ndarray]) -> int:
    """Drop the resident pages of memory-mapped arrays (``madvise(MADV_DONTNEED)``): a frame
    read with ``mmap=True`` stops counting in the process's memory once it has been consumed.

    The arrays stay valid: a later access reads the pages from the file again. Only for
    mappings never written to since they were read: a copy-on-write mapping (the readers'
    ``mmap=True``) would lose what was written. Arrays that are not memory-mapped are left
    alone.

    Parameters
    ----------
    arrays : iterable of numpy.ndarray
        Arrays (or views of them) returned by :func:`read_frame` and the like.

    Returns
    -------
    int
        Bytes of mappings released (resident or not).
    """
    import mmap

    done: set[int] = set()
    released = 0
    for arr in arrays:
        base: object = arr
        while base is not None and not isinstance(base, mmap.mmap):
            base = getattr(base, "base", None)
        if not isinstance(base, mmap.mmap) or id(base) in done or not hasattr(base, "madvise") or base.closed:
            continue
        done.add(id(base))
        with contextlib.suppress(OSError, ValueError):
            base.madvise(mmap.MADV_DONTNEED)
            released += len(base)
    return released


def sha256_file(path: str | os.PathLike[str], chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file, read in chunks.

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    chunk : int
        Bytes read at a time.

    Returns
    -------
    str
        The 64-character hexadecimal digest.
    """
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


# The process's umask, read once at import (reading it means setting it, not thread-safe later).
_UMASK = os.umask(0o022)


os.umask(_UMASK)


def set_umask(mask: int) -> None:
    """Set the process's umask and the one the atomic writes give their files (read once at
    import): for a process that changes its umask after importing this module (a command forked
    from the command server).

    Parameters
    ----------
    mask : int
        The new umask, e.g. ``0o022``.
    """
    global _UMASK
    os.umask(mask)
    _UMASK = mask


#: errno values of file systems without hard links (exFAT/FAT, some network and FUSE mounts).
NO_HARD_LINKS = frozenset(
    e
    for e in (getattr(errno, n, None) for n in ("EPERM", "ENOTSUP", "EOPNOTSUPP", "ENOSYS", "EMLINK", "EXDEV"))
    if e is not None
)


def place_new(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> None:
    """Move ``src`` to ``dst`` without ever replacing an existing ``dst``.

    A hard link (``os.link`` fails when ``dst`` exists), then ``src`` is removed. Where the
    file system has no hard links (:data:`NO_HARD_LINKS`: exFAT/FAT USB sticks and SD cards),
    ``dst`` is first created exclusively (``O_CREAT | O_EXCL``: it fails when ``dst`` exists)
    and ``src`` renamed onto that placeholder; a crash in between leaves an empty ``dst``,
    which a reader rejects as unreadable.

    Parameters
    ----------
    src, dst : path
        Same folder (or file system).

    Raises
    ------
    FileExistsError
        ``dst`` exists.
    """
    try:
        os.link(src, dst)
    except FileExistsError:
        raise
    except OSError as err:
        if err.errno not in NO_HARD_LINKS:
            raise
        fd = os.open(dst, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        os.close(fd)
        os.replace(src, dst)
        return
    os.unlink(src)


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike[str], force: bool = False, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success move it into place atomically.

    Without ``force`` an existing ``path`` is never replaced (checked up front and again at
    the final step, :func:`place_new`: a hard link, or on file systems without hard links an
    exclusive create and a rename, so that a file created meanwhile is not clobbered).
    On error the temporary file is removed and ``path`` is untouched.

    Parameters
    ----------
    path : str or os.PathLike
        The output file.
    force : bool
        Replace an existing file.
    suffix : str, optional
        Suffix of the temporary file (default: that of ``path``), for writers that choose the
        format by the file name.

    Yields
    ------
    pathlib.Path
        The temporary file to write; it becomes ``path`` when the block ends without error.

    Raises
    ------
    OutputExistsError
        ``path`` exists (or appears while writing) and ``force`` is not given.
    InputError
        The output folder does not exist or is not writable.
    """
    path = check_new_output(path, force)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(f"{path}: output folder {parent} does not exist")
    if not os.access(parent, os.W_OK):
        raise InputError(f"{path}: output folder {parent} is not writable")
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix or ".tmp", dir=parent)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        # mkstemp creates the file private (0600); the output gets the permissions any new
        # file of this process gets (0666 minus the umask), like a plain open() would give it.
        os.chmod(tmp, 0o666 & ~_UMASK)
        if force:
            os.replace(tmp, path)
        else:
            try:
                place_new(tmp, path)
            except FileExistsError:
                raise OutputExistsError(f"{path}: appeared while writing; use --force to overwrite") from None
    finally:
        if tmp.exists():
            tmp.unlink()
