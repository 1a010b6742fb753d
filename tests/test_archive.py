"""The run archive: the documented xarray Dataset, per-run chunks, commit scheme (never a partial
run, readers undisturbed by appends), in-place rewrite, failure records, one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import zarr

from hdrcap.batch.archive import CHANNELS, RUN_COORDS, Archive, ArchiveRun, open_archive, read_run, stage_channels
from hdrcap.pipeline.errors import InputError

SHAPE = (6, 8)


def _run(i: int, seed: int | None = None, shape=SHAPE) -> ArchiveRun:
    rng = np.random.default_rng(i if seed is None else seed)
    irr = rng.lognormal(5, 2, shape).astype(np.float32)
    channels = {
        "irradiance": irr,
        "sigma": (0.05 * irr + 1).astype(np.float32),
        "nexp": rng.integers(0, 4, shape).astype(np.float32),
    }
    return ArchiveRun(
        folder=f"/runs/{i:03d}",
        start_time=f"2026-01-0{1 + i % 9}T10:00:00+00:00",
        channels=channels,
        header={"unit": "electrons per second per photosite", "i": i},
        exposure_times=[0.001, 0.01],
        plan=None,
        merge_options={"iterations": 20},
        calibration={"sha256": "ab" * 32},
    )


def test_documented_dataset(tmp_path):
    path = tmp_path / "a.zarr"
    runs = [_run(i) for i in range(3)]
    store = Archive(path)
    assert [store.commit(r) for r in runs] == [0, 1, 2]
    ds = xr.open_zarr(path)
    assert dict(ds.sizes) == {"run": 3, "y": SHAPE[0], "x": SHAPE[1]}
    for name in CHANNELS:
        assert ds[name].dims == ("run", "y", "x") and ds[name].dtype == np.float32
        assert ds[name].encoding["chunks"] == (1, *SHAPE)  # one chunk per run
        assert ds[name].attrs["long_name"]
    assert ds["irradiance"].attrs["units"] == ds["sigma"].attrs["units"] == "count s-1"
    assert set(RUN_COORDS) <= set(ds.coords) and all(ds[c].dims == ("run",) for c in RUN_COORDS)
    assert ds["start_time"].dtype.kind == "M" and ds.attrs["Conventions"].startswith("CF-")
    assert list(ds["run"].values) == [0, 1, 2]
    for i, r in enumerate(runs):
        for name in CHANNELS:
            np.testing.assert_array_equal(ds[name].isel(run=i).values, r.channels[name])
        assert str(ds["folder"].values[i]) == r.folder
        assert json.loads(str(ds["exposure_times"].values[i])) == r.exposure_times
        assert json.loads(str(ds["calibration"].values[i])) == r.calibration
    assert ds["start_time"].values[1] == np.datetime64("2026-01-02T10:00:00")
    # Appending writes new chunk files only: one per run per variable.
    assert sorted(p.name for p in (path / "irradiance").iterdir() if not p.name.startswith(".")) == [
        "0.0.0",
        "1.0.0",
        "2.0.0",
    ]


def test_read_run_and_errors(tmp_path):
    path = tmp_path / "a.zarr"
    store = Archive(path)
    store.commit(_run(0))
    img = read_run(path, 0)
    assert img.header == {"unit": "electrons per second per photosite", "i": 0}
    np.testing.assert_array_equal(img.sigma, _run(0).channels["sigma"])
    with pytest.raises(InputError, match="run 4 is not in the archive"):
        read_run(path, 4)
    with pytest.raises(InputError, match="differs from the archive"):
        store.commit(_run(1, shape=(4, 4)))
    with pytest.raises(InputError, match="already in"):
        store.commit(_run(0, seed=9))
    with pytest.raises(InputError, match="not an hdrcap archive"):
        open_archive(tmp_path)


def test_reader_undisturbed_by_appends_and_rewrite_in_place(tmp_path):
    path = tmp_path / "a.zarr"
    store = Archive(path)
    for i in range(2):
        store.commit(_run(i))
    reader = xr.open_zarr(path)  # a reader holding the first batch
    store.commit(_run(2))
    assert reader.sizes["run"] == 2
    np.testing.assert_array_equal(reader["irradiance"].isel(run=1).values, _run(1).channels["irradiance"])
    assert xr.open_zarr(path).sizes["run"] == 3
    # --force: the run of the same folder is rewritten in place, never duplicated
    new = _run(1, seed=42)
    assert store.commit(new, replace=True) == 1
    ds = xr.open_zarr(path)
    assert ds.sizes["run"] == 3 and list(ds["folder"].values).count("/runs/001") == 1
    np.testing.assert_array_equal(ds["irradiance"].isel(run=1).values, new.channels["irradiance"])


def _staged(store: Archive, staging, run: ArchiveRun) -> ArchiveRun:
    """``run`` as a worker that sees the staging folder sends it: chunk files, no arrays."""
    files = stage_channels(staging, run.folder.replace("/", "_"), run.channels)
    assert set(files) == set(CHANNELS)
    return ArchiveRun(
        run.folder,
        run.start_time,
        {},
        run.header,
        run.exposure_times,
        run.plan,
        run.merge_options,
        run.calibration,
        staged=files,
        staged_shape=run.shape,
    )


def test_staged_runs_commit_by_renaming_chunk_files(tmp_path):
    path = tmp_path / "a.zarr"
    store = Archive(path)
    staging = store.open_staging()
    for i in range(3):  # the first creates the archive, the others are renamed into place
        store.commit(_staged(store, staging, _run(i)))
    assert stage_channels((staging[0], "another batch's token"), "x", _run(0).channels) == {}  # not seen: no staging
    assert not [p for p in Path(staging[0]).iterdir() if p.name != "token"]  # every staged file moved in
    store.close_staging(staging)
    assert not path.with_name("a.zarr.staging").exists()
    ds = xr.open_zarr(path)
    for i in range(3):
        for name in CHANNELS:
            np.testing.assert_array_equal(ds[name].isel(run=i).values, _run(i).channels[name])
    assert set(ds.coords) == {"run", *RUN_COORDS} and set(ds.data_vars) == set(CHANNELS)


@pytest.mark.parametrize("staged", [False, True])
def test_a_crash_before_the_commit_leaves_no_partial_run(tmp_path, monkeypatch, staged):
    path = tmp_path / "a.zarr"
    store = Archive(path)
    store.commit(_run(0))
    staging = store.open_staging()
    given = (lambda r: _staged(store, staging, r)) if staged else (lambda r: r)
    # The writer dies after writing the run's arrays, before the consolidated metadata (the commit).
    real = zarr.consolidate_metadata

    def die(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(zarr, "consolidate_metadata", die)
    with pytest.raises(KeyboardInterrupt):
        store.commit(given(_run(1)))
    monkeypatch.setattr(zarr, "consolidate_metadata", real)
    raw = zarr.open_group(path, mode="r", use_consolidated=False, zarr_format=2)
    assert raw["irradiance"].shape[0] == 2  # the arrays did grow ...
    ds = xr.open_zarr(path)
    assert ds.sizes["run"] == 1 and list(ds["folder"].values) == ["/runs/000"]  # ... readers see no partial run
    # The next writer cuts the uncommitted run off and appends in its place.
    assert store.commit(given(_run(2))) == 1
    ds = xr.open_zarr(path)
    assert list(ds["folder"].values) == ["/runs/000", "/runs/002"]
    np.testing.assert_array_equal(ds["nexp"].isel(run=1).values, _run(2).channels["nexp"])


def test_failures_recorded_until_the_run_lands(tmp_path):
    path = tmp_path / "a.zarr"
    store = Archive(path)
    store.record_failure("/runs/001", "InputError: truncated raw file")
    assert store.folders() == {} and store.failed()["/runs/001"]["error"] == "InputError: truncated raw file"
    assert xr.open_zarr(path).sizes["run"] == 0
    store.commit(_run(0))
    store.record_failure("/runs/002", "boom")
    assert set(store.failed()) == {"/runs/001", "/runs/002"}
    store.commit(_run(1))
    assert set(store.failed()) == {"/runs/002"}
    assert json.loads(xr.open_zarr(path).attrs["hdrcap_failed_runs"]).keys() == {"/runs/002"}
