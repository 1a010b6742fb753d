"""A small fuzz budget for every parser (the nightly budget: ``python tests/fuzzing.py``).

Every input must end in a result or a one-line ``hdrcap: error:`` with exit status 2 (see
``tests/fuzzing.py``). Inputs that once broke the contract are stored under
``tests/data/fuzz/<target>/`` and replayed here.
"""

from __future__ import annotations

import pytest
from fuzzing import DATA, TARGETS, build_corpus, check_outcome, run_target
from hypothesis import HealthCheck, given, settings

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
