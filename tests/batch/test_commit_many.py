"""Several runs committed together (what ``hdrcap batch`` does with the runs reported while the
previous commit was made): the archive equals the one of commits made one by one; a crash before
the commit leaves none of them; a rewrite among new runs goes in the same commit."""

from __future__ import annotations

import json

import numpy as np
import xarray as xr

from hdrcap.batch.archive import CHANNELS, RUN_COORDS, Archive
from tests.helpers.archive import archive_run, commit_interrupted


def _archive(path, groups):
    """An archive of runs 0..n committed in ``groups`` (lists of run indices) with commit_many."""
    store = Archive(path)
    return [store.commit_many([archive_run(i) for i in g]) for g in groups]


def test_runs_committed_together_equal_runs_committed_one_by_one(tmp_path):
    together = _archive(tmp_path / "t.zarr", [[0], [1, 2, 3], [4, 5]])
    single = _archive(tmp_path / "s.zarr", [[i] for i in range(6)])
    assert together == [[0], [1, 2, 3], [4, 5]] and [n[0] for n in single] == list(range(6))
    a, b = xr.open_zarr(tmp_path / "t.zarr"), xr.open_zarr(tmp_path / "s.zarr")
    for name in (*CHANNELS, *RUN_COORDS, "run"):
        np.testing.assert_array_equal(a[name].values, b[name].values)
    assert a.attrs == b.attrs
    for i in range(6):
        np.testing.assert_array_equal(a["irradiance"].isel(run=i).values, archive_run(i).channels["irradiance"])
        assert json.loads(str(a["header"].values[i]))["i"] == i


def test_a_session_commits_once_per_commit_call(tmp_path):
    store = Archive(tmp_path / "a.zarr")
    with store.writer() as session:
        for i in range(5):
            session.add(session.write(archive_run(i)))
        assert session.commit() == {f"/runs/{i:03d}": i for i in range(5)}
        assert session.commits == 1
    assert session.commits == 1  # nothing left for the final commit


def test_a_crash_before_the_commit_leaves_none_of_the_runs(tmp_path, monkeypatch):
    path = tmp_path / "a.zarr"
    store = Archive(path)
    store.commit(archive_run(0))
    with commit_interrupted(monkeypatch):
        store.commit_many([archive_run(i) for i in (1, 2)])
    assert xr.open_zarr(path).sizes["run"] == 1
    assert store.commit_many([archive_run(i) for i in (3, 4)]) == [1, 2]
    assert list(xr.open_zarr(path)["folder"].values) == ["/runs/000", "/runs/003", "/runs/004"]


def test_a_rewrite_among_new_runs(tmp_path):
    path = tmp_path / "a.zarr"
    store = Archive(path)
    assert store.commit_many([archive_run(0), archive_run(1)]) == [0, 1]
    # a rewrite of a committed run among new ones: in place, the new one appended
    assert store.commit_many([archive_run(1, seed=9), archive_run(2)], replace=True) == [1, 2]
    ds = xr.open_zarr(path)
    np.testing.assert_array_equal(ds["irradiance"].isel(run=1).values, archive_run(1, seed=9).channels["irradiance"])
    np.testing.assert_array_equal(ds["irradiance"].isel(run=2).values, archive_run(2).channels["irradiance"])
    assert list(ds["folder"].values) == ["/runs/000", "/runs/001", "/runs/002"]
    assert list(ds["run"].values) == [0, 1, 2]
