"""Fuzzing of every file hdrcap parses: seed corpus, mutations, targets and the outcome rule.

Each target feeds one input file to the command that parses it (in-process, through the same
``main`` the ``hdrcap`` script runs) and checks the contract for input that hdrcap did not
write: a result (exit 0) or a one-line ``hdrcap: error: ...`` with exit status 2; never a
traceback, an internal error, a hang, or a result built from garbage.

Inputs are valid seed files (written by the simulator and the commands themselves) mutated at
the byte level (flips, overwrites, truncation, insertion, duplication of a chunk; offsets
biased towards the headers where parsers decide), and, for the text formats, generated
documents of the right shape with wrong values.

``tests/end_to_end/test_fuzz.py`` runs a small budget of examples in ``make test``. The nightly
command runs one target (or all) for a time budget and prints one JSON line per target (from the
repository root; ``.venv/bin/python tests/helpers/fuzzing.py ...`` runs the same)::

    .venv/bin/python -m tests.helpers.fuzzing --minutes 30 [--target dng] [--corpus DIR]

A failure does not end a target's budget: its input is shrunk and stored, and fuzzing goes on
with a fresh random seed; the JSON line lists every distinct failure (exception type, first line,
location) with its count and the smallest input found, stored under ``tests/data/fuzz/<target>/``
(``--save DIR``). Give a stored input a name that says what it was and it is a regression test
(``test_fuzz.py`` replays every file there).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import random
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from hypothesis import strategies as st

DATA = Path(__file__).resolve().parents[1] / "data" / "fuzz"

#: Seconds hypothesis may go on shrinking a failure after a target's time budget.
SHRINK_S = 300

#: Seconds one call may take before it counts as a hang (the seeds take well under 1 s).
CALL_TIMEOUT_S = 20


# ------------------------------------------------------------------------------- seed corpus


def _cli(*args) -> tuple[int, str, str]:
    """Run ``hdrcap ARGS`` in this process; return (exit status, stdout, stderr)."""
    from hdrcap.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in args])
    return rc, out.getvalue(), err.getvalue()


def _must(*args) -> str:
    rc, out, err = _cli(*args)
    if rc != 0:
        raise RuntimeError(f"seed corpus: hdrcap {' '.join(map(str, args))} failed ({rc}): {err}")
    return out


def _simulate(out: Path, seed: int, *options) -> None:
    """``hdrcap simulate`` of 64x48 camera-B files into ``out``."""
    _must("simulate", "--camera", "camera-B", "--size", "64x48", *options, "--seed", seed, "--out", out, "--force")


def _emva_set(folder: Path) -> Path:
    """A small EMVA 1288 descriptor (Release 3.0 layout) with 12-bit PNG images of a
    simulated linear camera: 6 exposure times, 2 bright + 2 dark images each."""
    import numpy as np
    from PIL import Image

    rng = np.random.default_rng(11)
    img_dir = folder / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    lines = ["v 3.0", "n 12 32 24"]
    for k, t_us in enumerate((100, 200, 400, 800, 1600, 3200)):
        photons = 2.0 * t_us
        lines.append(f"b {t_us * 1000:.1f} {photons:.1f}")
        for j in range(2):
            v = 30 + 0.3 * rng.poisson(0.5 * photons, (24, 32)) + rng.normal(0, 2, (24, 32))
            name = f"b_{k:03d}_{j}.png"
            Image.fromarray(np.clip(np.round(v), 0, 4095).astype(np.uint16)).save(img_dir / name)
            lines.append(f"i images\\{name}")
        lines.append(f"d {t_us * 1000:.1f}")
        for j in range(2):
            v = 30 + rng.normal(0, 2, (24, 32))
            name = f"d_{k:03d}_{j}.png"
            Image.fromarray(np.clip(np.round(v), 0, 4095).astype(np.uint16)).save(img_dir / name)
            lines.append(f"i images\\{name}")
    path = folder / "EMVA1288_Data.txt"
    path.write_text("\n".join(lines) + "\n")
    return path


JOB_TOML = """\
[job]
name = "fuzz"

[camera]
backend = "mock"
preset = "camera-B"
size = "64x48"
seed = 0

[scene]
name = "hdr"
decades = 3.0

[exposure]
mode = "bracket"
times = [0.001, 0.01, 0.1]
repeats = 1

[darks]
strategy = "model"

[calibration]
preset = "camera-B"

[output]
folder = "runs/{job}"
exr = "hdr.exr"
"""


def _libraw_dng(src: Path, dst: Path) -> Path:
    """``src`` (a simulator DNG) without DateTimeOriginal, so that :func:`read_raw` leaves it to
    LibRaw: the tag of that entry in the EXIF IFD becomes DateTimeDigitized (36868)."""
    import struct

    blob = bytearray(src.read_bytes())
    ifd0 = struct.unpack_from("<I", blob, 4)[0]
    entries = [ifd0 + 2 + 12 * i for i in range(struct.unpack_from("<H", blob, ifd0)[0])]
    exif = next(
        struct.unpack_from("<I", blob, e + 8)[0] for e in entries if struct.unpack_from("<H", blob, e)[0] == 34665
    )
    for i in range(struct.unpack_from("<H", blob, exif)[0]):
        pos = exif + 2 + 12 * i
        if struct.unpack_from("<H", blob, pos)[0] == 36867:
            struct.pack_into("<H", blob, pos, 36868)
    dst.write_bytes(bytes(blob))
    return dst


def _tiff_frames(frames: tuple[Path, ...], folder: Path) -> tuple[Path, ...]:
    """The mosaics of ``frames`` as single-channel 16-bit TIFF files (exposure times via --times)."""
    import tifffile

    from hdrcap.pipeline.io.raw import read_raw

    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i, frame in enumerate(frames):
        path = folder / f"frame_{i}.tif"
        if not path.exists():
            tifffile.imwrite(path, read_raw(frame, mmap=False).data)
        out.append(path)
    return tuple(out)


@dataclass(frozen=True)
class Corpus:
    """Valid seed files, one or more per parser."""

    root: Path
    frames: tuple[Path, ...]
    darks: tuple[Path, ...]
    libraw_dng: Path
    tiffs: tuple[Path, ...]
    times: tuple[float, ...]
    exr: Path
    merged: Path
    calibration: Path
    plan: Path
    plan_frames: tuple[Path, ...]
    plan_darks: tuple[Path, ...]
    job: Path
    manifest: Path
    events: Path
    emva: Path


def build_corpus(root: Path) -> Corpus:
    """Write the seed corpus into ``root`` (a few seconds; 64x48 frames)."""
    root = Path(root)
    sim = root / "sim"
    if not (sim / "truth.exr").exists():
        _simulate(sim, 2, "--times", "0.001", "0.01", "0.1", "--darks")
    frames = tuple(sorted(sim.glob("frame_*.dng")))
    darks = tuple(sorted(sim.glob("dark_*.dng")))
    cal_dir = root / "calset"
    cal = root / "camera.cal"
    if not cal.exists():
        _simulate(cal_dir, 3, "--calibration-set")
        bias = sorted(cal_dir.glob("bias_*"))
        sat = sorted(cal_dir.glob("sat*"))
        flats = sorted(cal_dir.glob("flat_*"))
        dark = sorted(cal_dir.glob("dark_*"))
        args = ["calibrate", "--bias", *bias, "--saturation", *sat, "--flat", *flats]
        if dark:
            args += ["--dark", *dark]
        _must(*args, "-o", cal, "--force")
    plan = root / "plan.json"
    if not plan.exists():
        plan.write_text(
            _must("plan", "--camera", "camera-B", "--irradiance", sim / "truth.exr", "--target-snr-db", "20", "--json")
        )
    plan_sim = root / "plansim"
    if not (plan_sim / "truth.exr").exists():
        times = sorted({float(t) for t in json.loads(plan.read_text())["exposures"]})
        _simulate(plan_sim, 4, "--times", *times, "--darks")
    plan_frames = tuple(sorted(plan_sim.glob("frame_*.dng")))
    plan_darks = tuple(sorted(plan_sim.glob("dark_*.dng")))
    job = root / "job.toml"
    job.write_text(JOB_TOML)
    run_dir = root / "runs" / "fuzz"
    if not (run_dir / "manifest.jsonl").exists():
        cwd = os.getcwd()
        os.chdir(root)
        try:
            _must("run", job, "--no-progress")
        finally:
            os.chdir(cwd)
    emva_dir = root / "emva"
    emva = emva_dir / "EMVA1288_Data.txt"
    if not emva.exists():
        _emva_set(emva_dir)
    from hdrcap.pipeline.io.raw import read_raw

    libraw_dng = _libraw_dng(frames[0], root / "libraw.dng")
    times = tuple(read_raw(f).exposure_time for f in frames)
    return Corpus(
        root,
        frames,
        darks,
        libraw_dng,
        _tiff_frames(frames, root / "tiff"),
        times,
        sim / "truth.exr",
        run_dir / "hdr.exr",
        cal,
        plan,
        plan_frames,
        plan_darks,
        job,
        run_dir / "manifest.jsonl",
        run_dir / "events.jsonl",
        emva,
    )


# --------------------------------------------------------------------------------- mutations


@st.composite
def mutated(draw, seed: bytes, header: int = 4096) -> bytes:
    """``seed`` with 1-8 byte-level mutations; offsets favour the first ``header`` bytes."""
    data = bytearray(seed)
    for _ in range(draw(st.integers(1, 8))):
        if not data:
            break
        n = len(data)
        near = draw(st.booleans())
        pos = draw(st.integers(0, min(n, header) - 1)) if near else draw(st.integers(0, n - 1))
        op = draw(st.sampled_from(["flip", "byte", "word", "truncate", "insert", "duplicate", "zero"]))
        if op == "flip":
            data[pos] ^= 1 << draw(st.integers(0, 7))
        elif op == "byte":
            data[pos] = draw(st.integers(0, 255))
        elif op == "word":
            word = draw(st.sampled_from([0, 0xFFFFFFFF, 0x7FFFFFFF, 0x80000000, 1, n, n + 1, 2 * n]))
            data[pos : pos + 4] = word.to_bytes(4, draw(st.sampled_from(["little", "big"])))
        elif op == "truncate":
            del data[pos:]
        elif op == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=16))
        elif op == "duplicate":
            size = draw(st.integers(1, 64))
            data[pos:pos] = data[pos : pos + size]
        else:
            size = draw(st.integers(1, 256))
            data[pos : pos + size] = bytes(len(data[pos : pos + size]))
    return bytes(data)


_JSON_LEAF = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**63), 2**63),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
)
JSON_VALUES = st.recursive(
    _JSON_LEAF,
    lambda inner: st.one_of(st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=12), inner, max_size=5)),
    max_leaves=20,
)


@st.composite
def json_like(draw, seed: bytes) -> bytes:
    """A JSON document of the seed's shape with some values replaced by arbitrary ones."""
    try:
        doc = json.loads(seed)
    except ValueError:
        return draw(mutated(seed))

    def walk(node):
        if isinstance(node, dict):
            out = {}
            for k, v in node.items():
                if draw(st.integers(0, 9)) == 0:
                    continue  # drop the key
                out[k] = draw(JSON_VALUES) if draw(st.integers(0, 5)) == 0 else walk(v)
            return out
        if isinstance(node, list):
            return [walk(v) for v in node] if draw(st.booleans()) else draw(JSON_VALUES)
        return node

    return json.dumps(walk(doc), allow_nan=True).encode()


TOML_VALUES = st.one_of(
    st.integers(-(2**70), 2**70).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(
        lambda f: {"nan": "nan", "inf": "inf", "-inf": "-inf"}.get(str(f), repr(f))
    ),
    st.text(max_size=12).map(json.dumps),
    st.sampled_from(["true", "false", "[]", "{}", "[1, 2]", '""', "-0", "1e308"]),
)


@st.composite
def toml_like(draw, seed: bytes) -> bytes:
    """The seed's TOML with some values replaced, lines dropped or duplicated."""
    out = []
    for line in seed.decode().splitlines():
        roll = draw(st.integers(0, 11))
        if "=" in line and roll == 0:
            key = line.split("=", 1)[0]
            out.append(f"{key}= {draw(TOML_VALUES)}")
        elif roll == 1:
            continue
        elif roll == 2:
            out += [line, line]
        else:
            out.append(line)
    return "\n".join(out).encode()


# ----------------------------------------------------------------------------------- targets


class Hang(Exception):
    pass


@contextlib.contextmanager
def _time_limit(seconds: int):
    def handler(signum, frame):
        raise Hang(f"no answer within {seconds} s")

    old = signal.signal(signal.SIGALRM, handler)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


@dataclass(frozen=True)
class Outcome:
    """What one call of a target gave: exit status, its output streams, and whether the EXR it
    wrote (if any) is finite everywhere."""

    rc: int
    stdout: str
    stderr: str
    output_finite: bool = True


#: Resident memory (MiB) one call may add to what the fuzzing process held before it (its peak
#: minus its resident set before the call) before it counts as unbounded: the inputs are a few kB
#: to a few hundred kB, their results a few MB.
MEMORY_LIMIT_MIB = 1024


def _reset_peak() -> None:
    """Reset the process's peak resident memory (Linux: ``5`` to /proc/self/clear_refs)."""
    with contextlib.suppress(OSError):
        Path("/proc/self/clear_refs").write_text("5")


def _status_mib(field: str) -> float:
    """A memory field of /proc/self/status (``VmHWM``, ``VmRSS``), MiB (0 where unknown)."""
    try:
        status = Path("/proc/self/status").read_text()
    except OSError:
        return 0.0
    return next((int(line.split()[1]) / 1024 for line in status.splitlines() if line.startswith(field + ":")), 0.0)


def _peak_mib() -> float:
    """Peak resident memory since the last :func:`_reset_peak`, MiB (0 where unknown)."""
    return _status_mib("VmHWM")


def _exr_is_finite(path: Path) -> bool:
    import numpy as np

    from hdrcap.pipeline.io.exr import read_exr

    return all(np.isfinite(ch).all() for ch in read_exr(path).channels.values())


def check_outcome(outcome: Outcome, what: str) -> None:
    """The contract: exit 0 (with nothing but ``hdrcap: warning:`` lines on stderr and a finite
    output), or exit 2 with one ``hdrcap: error:`` line (warnings allowed)."""
    lines = [ln for ln in outcome.stderr.splitlines() if ln.strip() and not ln.startswith("hdrcap: warning:")]
    assert "Traceback" not in outcome.stderr, f"{what}: traceback\n{outcome.stderr}"
    assert "internal error" not in outcome.stderr, f"{what}: {outcome.stderr.strip()}"
    if outcome.rc == 0:
        assert not lines, f"{what}: a success that printed more than warnings on stderr: {lines[0]}\n{outcome.stderr}"
        assert outcome.output_finite, f"{what}: a success whose output holds NaN or infinite values"
        return
    assert outcome.rc == 2, f"{what}: exit status {outcome.rc}: {outcome.stderr.strip()}"
    assert len(lines) == 1 and lines[0].startswith("hdrcap: error: "), (
        f"{what}: expected one 'hdrcap: error:' line, got: {(lines + [''])[0]}\n{outcome.stderr}"
    )


def run_target(target: str, corpus: Corpus, data: bytes, work: Path, timeout: float | None = None) -> Outcome:
    """Write ``data`` as the input of ``target`` in ``work`` and run the command that parses it,
    within ``timeout`` seconds (default ``CALL_TIMEOUT_S``; 0: no limit)."""
    work.mkdir(parents=True, exist_ok=True)
    out = work / "out.exr"
    out.unlink(missing_ok=True)
    f = TARGETS[target]
    path = work / f.name
    path.write_bytes(data)
    args = f.args(corpus, path, out)
    _reset_peak()
    before = _status_mib("VmRSS")  # what the process held already (libraries, caches, freed-but-kept heap)
    limit = CALL_TIMEOUT_S if timeout is None else timeout
    t0 = time.monotonic()
    with _time_limit(limit) if limit else contextlib.nullcontext():
        if callable(args):
            outcome = args()
        else:
            outcome = Outcome(*_cli(*args))
    took = time.monotonic() - t0
    if limit and took > limit:  # over the limit all the same: the alarm landed where it is swallowed
        # (a finalizer prints "Exception ignored ... Traceback" and the call goes on): a hang, not a
        # traceback; the alarm's own message, so that failure_key counts both as one failure
        raise Hang(f"no answer within {limit} s")
    grew = _peak_mib() - before
    assert grew < MEMORY_LIMIT_MIB, f"{target}: the call took {grew:.0f} MiB above the {before:.0f} MiB held before it"
    if outcome.rc == 0 and out.exists():
        outcome = Outcome(outcome.rc, outcome.stdout, outcome.stderr, _exr_is_finite(out))
    return outcome


def _library_call(fn: Callable[[], object]) -> Callable[[], Outcome]:
    """Targets without a command of their own (manifest, event log): the library function must
    return or raise :class:`HdrcapError`, which the command line prints as one line."""
    from hdrcap.pipeline.errors import HdrcapError

    def call() -> Outcome:
        try:
            fn()
        except HdrcapError as err:
            return Outcome(2, "", f"hdrcap: error: {err}\n")
        return Outcome(0, "", "")

    return call


def _manifest_target(corpus: Corpus, path: Path, out: Path):
    from hdrcap.acquire.capture.manifest import Manifest

    run = path.parent / "run"
    run.mkdir(exist_ok=True)
    (run / "manifest.jsonl").write_bytes(path.read_bytes())

    def read():
        m = Manifest(run)
        m.records()
        m.header()
        m.frames()

    return _library_call(read)


def _events_target(corpus: Corpus, path: Path, out: Path):
    from hdrcap.acquire.capture.manifest import EventLog

    run = path.parent / "run"
    run.mkdir(exist_ok=True)
    (run / "events.jsonl").write_bytes(path.read_bytes())
    return _library_call(lambda: EventLog(run).events())


def _emva_target(corpus: Corpus, path: Path, out: Path):
    # The descriptor names its images relative to its own folder: put it beside them.
    desc = corpus.emva.parent / f"fuzz_{os.getpid()}.txt"
    desc.write_bytes(path.read_bytes())
    return ["calibrate", "--emva", desc, "-o", path.parent / "emva.cal", "--force"]


@dataclass(frozen=True)
class Target:
    name: str  # file name of the input in the work folder
    seed: Callable[[Corpus], bytes]
    strategy: Callable[[bytes], st.SearchStrategy[bytes]]
    args: Callable[[Corpus, Path, Path], object]


TARGETS: dict[str, Target] = {
    "dng": Target(
        "input.dng",
        lambda c: c.frames[0].read_bytes(),
        mutated,
        lambda c, p, o: ["merge", p, *c.frames[1:], "--camera", "camera-B", "-o", o, "--force"],
    ),
    "dng-libraw": Target(
        "input.dng",
        lambda c: c.libraw_dng.read_bytes(),
        mutated,
        lambda c, p, o: ["merge", p, *c.frames[1:], "--camera", "camera-B", "-o", o, "--force"],
    ),
    "tiff": Target(
        "input.tif",
        lambda c: c.tiffs[0].read_bytes(),
        mutated,
        lambda c, p, o: ["merge", p, *c.tiffs[1:], "--times", *c.times, "--camera", "camera-B", "-o", o, "--force"],
    ),
    "dark-dng": Target(
        "dark.dng",
        lambda c: c.darks[0].read_bytes(),
        mutated,
        lambda c, p, o: ["merge", *c.frames, "--darks", p, *c.darks[1:], "--camera", "camera-B", "-o", o, "--force"],
    ),
    "exr-denoise": Target(
        "input.exr", lambda c: c.merged.read_bytes(), mutated, lambda c, p, o: ["denoise", p, "-o", o, "--force"]
    ),
    "exr-develop": Target(
        "input.exr",
        lambda c: c.merged.read_bytes(),
        mutated,
        lambda c, p, o: ["develop", p, "-o", o, "--space", "linear-srgb", "--force"],
    ),
    "exr-plan": Target(
        "map.exr",
        lambda c: c.exr.read_bytes(),
        mutated,
        lambda c, p, o: ["plan", "--camera", "camera-B", "--irradiance", p, "--target-snr-db", "20"],
    ),
    "calibration": Target(
        "camera.cal",
        lambda c: c.calibration.read_bytes(),
        mutated,
        lambda c, p, o: ["merge", *c.frames, "--calibration", p, "-o", o, "--force"],
    ),
    "plan-json": Target(
        "plan.json",
        lambda c: c.plan.read_bytes(),
        lambda s: st.one_of(json_like(s), mutated(s)),
        lambda c, p, o: [
            "merge",
            *c.plan_frames,
            "--darks",
            *c.plan_darks,
            "--camera",
            "camera-B",
            "--plan",
            p,
            "-o",
            o,
            "--force",
        ],
    ),
    "job-toml": Target(
        "job.toml",
        lambda c: c.job.read_bytes(),
        lambda s: st.one_of(toml_like(s), mutated(s)),
        lambda c, p, o: ["run", p, "--check"],
    ),
    "manifest": Target(
        "manifest.jsonl",
        lambda c: c.manifest.read_bytes(),
        lambda s: st.one_of(mutated(s), json_like(s)),
        _manifest_target,
    ),
    "events": Target("events.jsonl", lambda c: c.events.read_bytes(), mutated, _events_target),
    "emva": Target("EMVA1288_Data.txt", lambda c: c.emva.read_bytes(), mutated, _emva_target),
}


# --------------------------------------------------------------------------- nightly command

#: The repository root: a failure's location is its innermost frame in hdrcap's own code.
REPO = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class FailureKey:
    """What makes two failures the same bug: exception type, first line of its message (numbers of
    three or more digits and hex addresses replaced by ``N``), and location (``file:line``)."""

    error: str
    message: str
    location: str


def _location(err: BaseException) -> str:
    """Innermost frame of ``err`` in hdrcap's code (else the innermost of all); for a broken
    contract the innermost frame of the traceback it printed, else the rule that failed."""
    import re
    import traceback

    if isinstance(err, Hang):  # where the alarm struck says nothing
        return ""
    printed = re.findall(r'File "([^"]+)", line (\d+)', str(err))
    if printed:
        return f"{_relative(printed[-1][0])}:{printed[-1][1]}"
    frames = traceback.extract_tb(err.__traceback__)
    ours = [f for f in frames if _is_ours(f.filename)]
    frame = (ours or frames or [None])[-1]
    return f"{_relative(frame.filename)}:{frame.lineno}" if frame else ""


def _is_ours(filename: str) -> bool:
    path = Path(filename).resolve()
    return path.is_relative_to(REPO) and not path.is_relative_to(REPO / ".venv")


def _relative(filename: str) -> str:
    path = Path(filename).resolve()
    return str(path.relative_to(REPO)) if path.is_relative_to(REPO) else path.name


def failure_key(err: BaseException) -> FailureKey:
    """The :class:`FailureKey` of an exception raised by a target call or its contract check."""
    import re

    text = str(err).strip()
    first = text.splitlines()[0] if text else ""
    first = re.sub(r"0x[0-9a-fA-F]+|\d{3,}", "N", first)[:300]
    return FailureKey(type(err).__name__, first, _location(err))


@dataclass
class Failure:
    """One distinct failure: how often it occurred and the smallest input (shortlex, the order
    hypothesis shrinks in) that gave it."""

    key: FailureKey
    count: int = 0
    data: bytes = b""
    saved: Path | None = None

    def seen(self, data: bytes) -> None:
        self.count += 1
        if self.count == 1 or (len(data), data) < (len(self.data), self.data):
            self.data = data

    def save(self, folder: Path) -> None:
        """Write the smallest input to ``folder/<sha256 prefix>.bin`` (replacing a larger one)."""
        import hashlib

        path = folder / (hashlib.sha256(self.data).hexdigest()[:16] + ".bin")
        if path == self.saved:
            return
        folder.mkdir(parents=True, exist_ok=True)
        path.write_bytes(self.data)
        if self.saved is not None:
            self.saved.unlink(missing_ok=True)
        self.saved = path

    def report(self) -> dict:
        return {
            "error": self.key.error,
            "message": self.key.message,
            "location": self.key.location,
            "count": self.count,
            "size": len(self.data),
            "saved": str(self.saved) if self.saved else None,
        }


#: Seconds one call may run before the watchdog gives it up as stuck: the alarm of
#: ``CALL_TIMEOUT_S`` cannot stop a hang in a worker thread (the main thread then waits for it).
STUCK_S = 3 * CALL_TIMEOUT_S


class _Watchdog:
    """A daemon thread that calls ``on_stuck(data)`` once a call has run for ``seconds``."""

    def __init__(self, seconds: float, on_stuck: Callable[[bytes], None]):
        self.seconds, self.on_stuck = seconds, on_stuck
        self.since: float | None = None
        self.data = b""
        self.stop = threading.Event()
        threading.Thread(target=self._watch, daemon=True, name="fuzz-watchdog").start()

    @contextlib.contextmanager
    def call(self, data: bytes):
        self.data, self.since = data, time.monotonic()
        try:
            yield
        finally:
            self.since = None

    def _watch(self) -> None:
        while not self.stop.wait(min(1.0, self.seconds / 4)):
            since = self.since
            if since is not None and time.monotonic() - since > self.seconds:
                self.since = None
                self.on_stuck(self.data)


def fuzz(
    strategy: st.SearchStrategy[bytes],
    call: Callable[[bytes], object],
    seconds: float,
    save: Path | None = None,
    shrink_s: float = SHRINK_S,
    rng: random.Random | None = None,
    stuck_s: float | None = None,
    on_stuck: Callable[[dict], None] | None = None,
) -> dict:
    """Feed inputs drawn from ``strategy`` to ``call`` for ``seconds``, going on after failures.

    Each round is a hypothesis run with a fresh random seed. An exception of ``call`` with a new
    :class:`FailureKey` ends the round after hypothesis has shrunk it (for at most ``shrink_s``
    past the budget); its smallest input is stored under ``save`` and the next round starts.
    Inputs that fail in a known way are counted, not shrunk again. ``rng`` draws the rounds'
    seeds (default: the system's entropy). A call still running after ``stuck_s`` (default
    ``STUCK_S``) is a ``Hang`` failure, stored at once (it cannot be shrunk); then ``on_stuck``
    receives the report so far (the call may never return).

    Returns
    -------
    dict
        ``executions``, ``seconds``, ``rounds`` (the hypothesis seeds), the slowest call (s) and
        ``failures``: one entry per distinct failure (error, message, location, count, size of
        the smallest input in bytes, where it was saved), the most frequent first.
    """
    from hypothesis import HealthCheck, Phase, Verbosity, given, settings
    from hypothesis import seed as hypothesis_seed

    stuck_s = STUCK_S if stuck_s is None else stuck_s
    t0 = time.monotonic()
    deadline = t0 + seconds
    failures: dict[FailureKey, Failure] = {}
    known: set[FailureKey] = set()
    stats = {"n": 0, "slowest": 0.0}
    seeds = []

    def report() -> dict:
        return {
            "executions": stats["n"],
            "seconds": round(time.monotonic() - t0, 1),
            "rounds": seeds,
            "slowest_call_s": round(stats["slowest"], 2),
            "failures": [f.report() for f in sorted(failures.values(), key=lambda f: -f.count)],
        }

    def stuck(data: bytes) -> None:
        key = FailureKey("Hang", f"no answer within {stuck_s:g} s (a thread the time limit cannot stop)", "")
        known.add(key)
        failures.setdefault(key, Failure(key)).seen(data)
        if save is not None:
            failures[key].save(save)
        if on_stuck is not None:
            on_stuck(report())

    def one(data: bytes) -> None:
        now = time.monotonic()
        if now > deadline and (known.issuperset(failures) or now > deadline + shrink_s):
            raise _Done
        stats["n"] += 1
        try:
            with watchdog.call(data):
                call(data)
        except Exception as err:
            key = failure_key(err)
            failures.setdefault(key, Failure(key)).seen(data)
            if key not in known:
                raise  # hypothesis shrinks it
        finally:
            stats["slowest"] = max(stats["slowest"], time.monotonic() - now)

    watchdog = _Watchdog(stuck_s, stuck)
    try:
        while time.monotonic() < deadline:
            seeds.append((rng or random.SystemRandom()).getrandbits(64))
            run = settings(
                max_examples=10**9,
                deadline=None,
                database=None,
                phases=[Phase.generate, Phase.shrink],
                suppress_health_check=list(HealthCheck),
                verbosity=Verbosity.quiet,
            )(hypothesis_seed(seeds[-1])(given(strategy)(one)))
            with contextlib.suppress(_Done, Exception):  # what failed is in ``failures``
                run()
            known.update(failures)
            if save is not None:
                for failure in failures.values():
                    failure.save(save)
    finally:
        watchdog.stop.set()
    return report()


def fuzz_target(
    name: str,
    corpus: Corpus,
    work: Path,
    minutes: float,
    save: Path | None = None,
    on_stuck: Callable[[dict], None] | None = None,
) -> dict:
    """Run one target for ``minutes`` of mutated inputs (see :func:`fuzz`).

    Returns
    -------
    dict
        ``target``, the entries of :func:`fuzz`, ``exit_status`` (count of each) and the
        largest peak memory of a call (MiB).
    """
    rcs: dict[int, int] = {}
    peak = [0.0]

    def call(data: bytes) -> None:
        try:
            outcome = run_target(name, corpus, data, work / name)
        finally:
            peak[0] = max(peak[0], _peak_mib())
        rcs[outcome.rc] = rcs.get(outcome.rc, 0) + 1
        check_outcome(outcome, name)

    def report(result: dict) -> dict:
        return {"target": name, **result, "exit_status": rcs, "peak_mib": round(peak[0])}

    # warm-up, outside the time limits and the count: the unmutated seed once, so that numba
    # compiles (or loads from its cache) the kernels of this target's path before the first timed
    # call; a cold cache on a busy machine took 20-60 s and was reported as a hang
    warm = run_target(name, corpus, TARGETS[name].seed(corpus), work / name, timeout=0)
    check_outcome(warm, name)
    old = os.environ.get("HDRCAP_DEBUG")
    os.environ["HDRCAP_DEBUG"] = "1"  # an internal error raises: its location tells bugs apart
    try:
        strategy = TARGETS[name].strategy(TARGETS[name].seed(corpus))
        stuck = (lambda result: on_stuck(report(result))) if on_stuck else None
        result = fuzz(strategy, call, minutes * 60, save / name if save else None, on_stuck=stuck)
    finally:
        if old is None:
            del os.environ["HDRCAP_DEBUG"]
        else:
            os.environ["HDRCAP_DEBUG"] = old
    return report(result)


def nightly(
    minutes: float, targets: list[str], corpus_dir: Path, work: Path, save: Path | None = None, failed: bool = False
) -> int:
    """Run each target for ``minutes``; print one JSON line per target; exit 1 on a failure.

    A stuck call (see :func:`fuzz`) ends the target: its line is printed with the stacks of all
    threads on stderr, and the process replaces itself with a new one for the remaining targets.
    """
    corpus = build_corpus(corpus_dir)
    for k, name in enumerate(targets):

        def give_up(result: dict, rest: list[str] = targets[k + 1 :]) -> None:
            import faulthandler

            # the stuck call may have redirected sys.stdout and sys.stderr: the process's own
            print(json.dumps({**result, "stuck": True}), file=sys.__stdout__, flush=True)
            sys.__stderr__.flush()
            faulthandler.dump_traceback(sys.__stderr__, all_threads=True)
            if not rest:
                os._exit(1)
            args = [f"--minutes={minutes}", f"--corpus={corpus_dir}", "--failed-before"]
            args += [f"--target={t}" for t in rest] + ([f"--save={save}"] if save else ["--no-save"])
            env = {k: v for k, v in os.environ.items() if k != "HDRCAP_DEBUG"}
            os.execve(sys.executable, [sys.executable, str(Path(__file__).resolve()), *args], env)

        result = fuzz_target(name, corpus, work, minutes, save, on_stuck=give_up)
        failed |= bool(result["failures"])
        print(json.dumps(result), flush=True)
    return 1 if failed else 0


class _Done(BaseException):
    """Raised to end a time-boxed hypothesis run (a BaseException so hypothesis passes it up)."""


def main(argv: list[str] | None = None) -> int:
    import argparse
    import tempfile

    ap = argparse.ArgumentParser(description="hdrcap nightly fuzzing: every parser for a time budget.")
    ap.add_argument("--minutes", type=float, default=30.0, help="time budget per target (default 30)")
    ap.add_argument("--target", action="append", choices=sorted(TARGETS), help="target (repeatable; default all)")
    ap.add_argument("--corpus", type=Path, default=None, help="folder for the seed corpus (default: temporary)")
    ap.add_argument(
        "--save", type=Path, default=DATA, help="where to store shrunk failing inputs (default: tests/data/fuzz)"
    )
    ap.add_argument("--no-save", dest="save", action="store_const", const=None, help="store no failing inputs")
    ap.add_argument("--failed-before", action="store_true", help=argparse.SUPPRESS)  # after a stuck call
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="hdrcap-fuzz-") as tmp:
        corpus_dir = args.corpus or Path(tmp) / "corpus"
        targets = args.target or sorted(TARGETS)
        return nightly(args.minutes, targets, corpus_dir, Path(tmp) / "work", args.save, args.failed_before)


if __name__ == "__main__":
    sys.exit(main())
