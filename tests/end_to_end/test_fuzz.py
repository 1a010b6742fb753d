"""A small fuzz budget for every parser (the nightly budget: ``python -m tests.helpers.fuzzing``).

Every input must end in a result or a one-line ``hdrcap: error:`` with exit status 2 (see
``tests/helpers/fuzzing.py``). Inputs that once broke the contract are stored under
``tests/data/fuzz/<target>/`` and replayed here.
"""

from __future__ import annotations

import itertools
import random
import threading
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.helpers.fuzzing import DATA, TARGETS, build_corpus, check_outcome, failure_key, fuzz, run_target

EXAMPLES = 30


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    return build_corpus(tmp_path_factory.mktemp("fuzz-corpus"))


@pytest.mark.parametrize("name", sorted(TARGETS))
def test_seed_input_is_accepted(name, corpus, tmp_path):
    """The unmutated seed gives a result: the targets exercise the parsers, not their errors."""
    out = run_target(name, corpus, TARGETS[name].seed(corpus), tmp_path)
    check_outcome(out, name)
    assert out.rc == 0, out.stderr


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(TARGETS))
def test_mutated_inputs_keep_the_contract(name, corpus, tmp_path_factory):
    target = TARGETS[name]
    work = tmp_path_factory.mktemp(f"fuzz-{name}")

    @settings(
        max_examples=EXAMPLES, deadline=None, derandomize=True, database=None, suppress_health_check=list(HealthCheck)
    )
    @given(target.strategy(target.seed(corpus)))
    def check(data):
        check_outcome(run_target(name, corpus, data, work), name)

    check()


REGRESSIONS = sorted(p for p in DATA.glob("*/*") if p.is_file()) if DATA.is_dir() else []


@pytest.mark.parametrize("path", REGRESSIONS, ids=[f"{p.parent.name}/{p.name}" for p in REGRESSIONS])
def test_stored_crash_inputs(path, corpus, tmp_path):
    check_outcome(run_target(path.parent.name, corpus, path.read_bytes(), tmp_path), path.name)


def test_fuzzing_goes_on_after_a_failure(tmp_path):
    """The nightly loop stores each distinct failure's smallest input and keeps fuzzing."""

    def call(data: bytes) -> None:
        if data[:1] and data[0] % 2:
            raise ValueError("starts with an odd byte")
        if len(data) > 4:
            raise KeyError("long")

    result = fuzz(st.binary(max_size=8), call, seconds=4, save=tmp_path, shrink_s=10, rng=random.Random(1))
    found = {f["error"]: f for f in result["failures"]}
    assert set(found) == {"ValueError", "KeyError"}, result["failures"]
    assert Path(found["ValueError"]["saved"]).read_bytes() == b"\x01"
    assert Path(found["KeyError"]["saved"]).read_bytes() == bytes(5)
    assert len(result["rounds"]) >= 2
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(Path(f["saved"]).name for f in found.values())
    assert result["executions"] > sum(f["count"] for f in found.values())


def test_failure_key_ignores_numbers_and_tells_locations_apart():
    def fail(n):
        if n % 2:
            raise ValueError(f"index {n} out of range")
        raise ValueError(f"index {n} out of range")

    keys = []
    for n in (1001, 2003, 4000):
        try:
            fail(n)
        except ValueError as err:
            keys.append(failure_key(err))
    assert keys[0] == keys[1] != keys[2]
    assert keys[0].message == "index N out of range" and keys[0].location.startswith("tests/end_to_end/test_fuzz.py:")


def test_a_stuck_call_is_stored_and_reported(tmp_path):
    """A call the time limit cannot stop (a hang in another thread) is a stored ``Hang`` failure."""
    release = threading.Event()
    reports = []

    def call(data: bytes) -> None:
        if data[:1] == b"\x05":
            release.wait()

    def on_stuck(report: dict) -> None:
        reports.append(report)
        release.set()

    result = fuzz(
        st.binary(max_size=8), call, seconds=4, save=tmp_path, rng=random.Random(2), stuck_s=1, on_stuck=on_stuck
    )
    assert len(reports) == 1 and [f["error"] for f in reports[0]["failures"]] == ["Hang"]
    (hang,) = result["failures"]
    assert Path(hang["saved"]).read_bytes()[:1] == b"\x05"


#: Decodes one file three times in a fresh interpreter: first thing, after another file, again.
_DECODE_IN_ORDER = """
import json, sys
from hdrcap.pipeline.io.raw import read_raw

def outcome(path):
    try:
        frame = read_raw(path, mmap=False)
    except Exception as err:
        return f"{type(err).__name__}: {err}"
    return [frame.cfa_pattern, int(frame.data.sum())]

first = outcome(sys.argv[1])
outcome(sys.argv[2])
print(json.dumps([first, outcome(sys.argv[1]), outcome(sys.argv[1])]))
"""


@pytest.mark.parametrize("name", ["cfa-pattern-without-entries.bin", "first-directory-unreadable.bin"])
def test_libraw_nondeterminism_is_refused_before_decoding(name, corpus, tmp_path):
    """LibRaw decodes these bytes to a different colour layout depending on what it decoded
    before (an uninitialised CFA buffer); hdrcap refuses them, the same way every time."""
    import json
    import subprocess
    import sys

    path = tmp_path / "input.dng"
    path.write_bytes((DATA / "dng-libraw" / name).read_bytes())
    run = subprocess.run(
        [sys.executable, "-c", _DECODE_IN_ORDER, str(path), str(corpus.libraw_dng)],
        capture_output=True,
        text=True,
        check=True,
    )
    outcomes = json.loads(run.stdout)
    assert outcomes[0] == outcomes[1] == outcomes[2], outcomes
    assert outcomes[0].startswith("InputError: ") and ("colour filter" in outcomes[0] or "directory" in outcomes[0])


def test_each_target_is_warmed_up_outside_the_time_limit(corpus, tmp_path, monkeypatch):
    """The nightly run first runs a target's unmutated seed without a time limit (numba compiles
    that path's kernels then; a cold cache on a busy machine was reported as a hang), and every
    call it counts afterwards is timed."""
    from tests.helpers import fuzzing

    limited, timeouts = [], []
    real_limit, real_run = fuzzing._time_limit, fuzzing.run_target

    def spy_limit(seconds):
        limited.append(seconds)
        return real_limit(seconds)

    def spy_run(*args, **kwargs):
        timeouts.append(kwargs.get("timeout"))
        return real_run(*args, **kwargs)

    monkeypatch.setattr(fuzzing, "_time_limit", spy_limit)
    monkeypatch.setattr(fuzzing, "run_target", spy_run)
    result = fuzzing.fuzz_target("events", corpus, tmp_path, minutes=0.02)
    assert timeouts[0] == 0 and not result["failures"]
    assert len(limited) == result["executions"] == len(timeouts) - 1 > 0
    assert set(limited) == {fuzzing.CALL_TIMEOUT_S}


def test_a_call_over_the_time_limit_is_a_hang_whatever_it_printed(corpus, tmp_path, monkeypatch):
    """The alarm can land in a finalizer, which prints 'Exception ignored ... Traceback' and lets
    the call finish: a call that took longer than the limit is a hang, not a traceback."""
    from tests.helpers import fuzzing

    ticks = itertools.count(0.0, 1e6)  # every reading a million seconds after the one before
    monkeypatch.setattr(fuzzing.time, "monotonic", lambda: next(ticks))
    with pytest.raises(fuzzing.Hang, match="no answer within"):
        fuzzing.run_target("events", corpus, TARGETS["events"].seed(corpus), tmp_path)
