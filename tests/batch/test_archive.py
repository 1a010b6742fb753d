"""The run archive: the documented xarray Dataset, per-run chunks that zarr-python reads and
writes alike, the calibration stored once, the commit scheme (never a partial run, readers
undisturbed by appends), slots taken without races by concurrent writers, a slot whose run never
comes filled, an interrupted session cleaned up, in-place rewrite, failure records, refusals."""

from __future__ import annotations

import json
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import zarr

from hdrcap.batch import archive as archive_mod
from hdrcap.batch import zarrv2
from hdrcap.batch.archive import (
    ARRAYS,
    CHANNELS,
    RUN_COORDS,
    Archive,
    Target,
    open_archive,
    read_run,
    write_run,
)
from hdrcap.pipeline.errors import InputError
from tests.helpers.archive import CALIBRATION, SHAPE, archive_run, commit_interrupted


def test_documented_dataset(tmp_path):
    path = tmp_path / "a.zarr"
    runs = [archive_run(i) for i in range(3)]
    store = Archive(path)
    assert [store.commit(r) for r in runs] == [0, 1, 2]
    ds = xr.open_zarr(path)
    assert dict(ds.sizes) == {"run": 3, "y": SHAPE[0], "x": SHAPE[1]}
    for name in CHANNELS:
        assert ds[name].dims == ("run", "y", "x") and ds[name].dtype == np.float32
        assert ds[name].encoding["chunks"] == (1, *SHAPE)  # one chunk per run
        assert ds[name].attrs["long_name"]
    assert ds["irradiance"].attrs["units"] == ds["sigma"].attrs["units"] == "count s-1"
    assert set(ds.coords) == {"run", *RUN_COORDS} and set(ds.data_vars) == set(CHANNELS)
    assert all(ds[c].dims == ("run",) for c in RUN_COORDS)
    assert ds["start_time"].dtype.kind == "M" and ds.attrs["Conventions"].startswith("CF-")
    assert list(ds["run"].values) == [0, 1, 2]
    for i, r in enumerate(runs):
        for name in CHANNELS:
            np.testing.assert_array_equal(ds[name].isel(run=i).values, r.channels[name])
        assert str(ds["folder"].values[i]) == r.folder
        assert json.loads(str(ds["exposure_times"].values[i])) == r.exposure_times
    assert ds["start_time"].values[1] == np.datetime64("2026-01-02T10:00:00")
    # The calibration is stored once and referenced by id, in the calibration coordinate and the header.
    table = json.loads(ds.attrs["hdrcap_calibrations"])
    assert list(table.values()) == [CALIBRATION] and set(map(str, ds["calibration"].values)) == set(table)
    assert json.loads(str(ds["header"].values[0]))["calibration"] in table
    assert read_run(path, 1).header == runs[1].header  # ... and given back in full
    # A run is one chunk file per array.
    assert sorted(p.name for p in (path / "irradiance").iterdir() if not p.name.startswith(".")) == [
        "0.0.0",
        "1.0.0",
        "2.0.0",
    ]


def test_two_calibrations_each_stored_once(tmp_path):
    other = {**CALIBRATION, "sha256": "cd" * 32, "params": {"gain": 0.7, "read_noise": 2.0}}
    runs = [archive_run(0), archive_run(1, calibration=other), archive_run(2)]
    store = Archive(tmp_path / "a.zarr")
    store.commit_many(runs)
    assert sorted(store.calibrations().values(), key=lambda c: c["sha256"]) == [CALIBRATION, other]
    for i, r in enumerate(runs):
        assert read_run(tmp_path / "a.zarr", i).header == r.header


def test_chunks_are_what_zarr_python_writes_and_reads(tmp_path):
    path = tmp_path / "a.zarr"
    run = archive_run(0)
    Archive(path).commit(run)
    group = zarr.open_group(path, mode="r", zarr_format=2)  # zarr-python, not xarray, not consolidated
    np.testing.assert_array_equal(group["sigma"][0], run.channels["sigma"])
    assert group["folder"][0] == run.folder and group["run"][:].tolist() == [0]
    # zarr-python writing the same values into arrays of the same metadata writes the same bytes
    ref = zarr.open_group(tmp_path / "ref.zarr", mode="w", zarr_format=2)
    for name, values in (("irradiance", run.channels["irradiance"][None]), ("folder", [run.folder]), ("run", [0])):
        meta = zarrv2.read_json(path / name / ".zarray")
        arr = ref.create_array(
            name,
            shape=meta["shape"],
            chunks=meta["chunks"],
            dtype=str if meta["dtype"] == "|O" else meta["dtype"],
            compressors=_blosc(),
            fill_value=None if meta["fill_value"] is None else np.nan,
            chunk_key_encoding={"name": "v2", "separator": "."},
            config={"write_empty_chunks": True},
        )
        arr[:] = np.asarray(values, dtype=object if meta["dtype"] == "|O" else meta["dtype"])
        assert zarrv2.read_json(tmp_path / "ref.zarr" / name / ".zarray") == meta, name
        key = zarrv2.chunk_name(0, len(meta["shape"]))
        assert (tmp_path / "ref.zarr" / name / key).read_bytes() == (path / name / key).read_bytes(), name


def _blosc():
    from numcodecs import Blosc

    return Blosc(cname="lz4", clevel=5, shuffle=Blosc.SHUFFLE)


def test_read_run_and_errors(tmp_path):
    path = tmp_path / "a.zarr"
    store = Archive(path)
    store.commit(archive_run(0))
    img = read_run(path, 0)
    assert img.header == archive_run(0).header
    np.testing.assert_array_equal(img.sigma, archive_run(0).channels["sigma"])
    with pytest.raises(InputError, match="run 4 is not in the archive"):
        read_run(path, 4)
    with pytest.raises(InputError, match="differs from the archive"):
        store.commit(archive_run(1, shape=(4, 4)))
    with pytest.raises(InputError, match="already in"):
        store.commit(archive_run(0, seed=9))
    with pytest.raises(InputError, match="not an hdrcap archive"):
        open_archive(tmp_path)
    assert xr.open_zarr(path).sizes["run"] == 1  # nothing of the refused runs
    assert sorted(os.listdir(path / "sigma")) == [".zarray", ".zattrs", "0.0.0"]
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="not an hdrcap archive"):
        Archive(tmp_path / "other").commit(archive_run(0))
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"


def test_an_archive_of_the_earlier_format_is_refused(tmp_path):
    path = tmp_path / "old.zarr"
    Archive(path).commit(archive_run(0))
    meta = json.loads((path / ".zmetadata").read_text())
    del meta["metadata"][".zattrs"]["hdrcap_archive_format"]  # as written before the calibration table
    (path / ".zmetadata").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="earlier hdrcap"):
        Archive(path).commit(archive_run(1))


def test_reader_undisturbed_by_appends_and_rewrite_in_place(tmp_path):
    path = tmp_path / "a.zarr"
    store = Archive(path)
    for i in range(2):
        store.commit(archive_run(i))
    reader = xr.open_zarr(path)  # a reader holding the first batch
    store.commit(archive_run(2))
    assert reader.sizes["run"] == 2
    np.testing.assert_array_equal(reader["irradiance"].isel(run=1).values, archive_run(1).channels["irradiance"])
    assert xr.open_zarr(path).sizes["run"] == 3
    # --force: the run of the same folder is rewritten in place, never duplicated
    new = archive_run(1, seed=42)
    assert store.commit(new, replace=True) == 1
    ds = xr.open_zarr(path)
    assert ds.sizes["run"] == 3 and list(ds["folder"].values).count("/runs/001") == 1
    np.testing.assert_array_equal(ds["irradiance"].isel(run=1).values, new.channels["irradiance"])
    assert list(ds["run"].values) == [0, 1, 2]
    assert not any(zarrv2.chunk_index(p.name) == 3 for p in (path / "irradiance").iterdir())  # its slot: gone


@pytest.mark.parametrize("runs_before", [0, 1])
def test_a_crash_before_the_commit_leaves_no_partial_run(tmp_path, monkeypatch, runs_before):
    path = tmp_path / "a.zarr"
    store = Archive(path)
    if runs_before:
        store.commit(archive_run(0))
    # The writer fails after writing the run's chunks, at the consolidated metadata (the commit).
    # (A writer killed outright: test_a_killed_session_is_cleaned_up_by_the_next.)
    with commit_interrupted(monkeypatch):
        store.commit(archive_run(1))
    if runs_before:
        ds = xr.open_zarr(path)
        assert ds.sizes["run"] == 1 and list(ds["folder"].values) == ["/runs/000"]  # readers see no partial run
        raw = zarr.open_group(path, mode="r", use_consolidated=False, zarr_format=2)
        assert raw["irradiance"].shape[0] == 1  # ... nor do readers of the per-array metadata
        assert not (path / "irradiance" / "1.0.0").exists()  # its chunk files are gone
    else:
        assert not store.exists()
    # The next writer cuts the uncommitted run off and appends in its place.
    assert store.commit(archive_run(2)) == runs_before
    ds = xr.open_zarr(path)
    assert list(ds["folder"].values) == ["/runs/000", "/runs/002"][1 - runs_before :]
    np.testing.assert_array_equal(ds["nexp"].isel(run=runs_before).values, archive_run(2).channels["nexp"])
    assert zarr.open_group(path, mode="r", use_consolidated=False, zarr_format=2)["sigma"].shape[0] == 1 + runs_before


def test_a_killed_session_is_cleaned_up_by_the_next(tmp_path):
    """A client killed mid-batch leaves chunk files beyond the committed runs and its staging
    folder; the next session removes them and reuses the slots."""
    path = tmp_path / "a.zarr"
    store = Archive(path)
    store.commit(archive_run(0))
    with store.writer() as session:  # a session that committed one run and wrote two more
        session.add(session.write(archive_run(1)))
        session.commit()
        session.write(archive_run(2))
        session.write(archive_run(3))
        staging = Path(session.target.staging)
        leftovers = {p: p.read_bytes() for p in path.rglob("*") if p.is_file()}
        session.close = lambda committed: None  # killed: no clean-up, no final commit
        session.commit = lambda final=False: {}
    for p, data in leftovers.items():  # as the killed client left the files
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
    assert staging.is_dir() and (path / "irradiance" / "3.0.0").is_file()
    assert xr.open_zarr(path).sizes["run"] == 2
    assert store.commit(archive_run(4)) == 2
    ds = xr.open_zarr(path)
    assert list(ds["folder"].values) == ["/runs/000", "/runs/001", "/runs/004"]
    np.testing.assert_array_equal(ds["sigma"].isel(run=2).values, archive_run(4).channels["sigma"])
    assert not staging.parent.exists()
    for name in ARRAYS:
        assert {zarrv2.chunk_index(p.name) for p in (path / name).iterdir()} - {None} == {0, 1, 2}, name


def _write_some(target: Target, indices: list[int]) -> list[tuple[str, int]]:
    """Another process writing runs at the same session (a batch worker)."""
    return [(e.folder, e.slot) for e in (write_run(target, archive_run(i)) for i in indices) if e is not None]


def test_concurrent_writers_take_distinct_slots(tmp_path):
    path = tmp_path / "a.zarr"
    store = Archive(path)
    store.commit(archive_run(0))
    parts = [list(range(1 + k, 25, 4)) for k in range(4)]
    with store.writer() as session:
        with ProcessPoolExecutor(4) as pool:
            written = [e for part in pool.map(_write_some, [session.target] * 4, parts) for e in part]
        slots = sorted(s for _f, s in written)
        assert slots == list(range(1, 25))  # every slot once: no two writers in one file
        reservations = {int(p.name): p.read_text() for p in (Path(session.target.staging) / "slots").iterdir()}
        assert reservations == {s: f for f, s in written}
        for folder, slot in written:
            i = int(folder.rsplit("/", 1)[1])
            session.add(archive_mod.RunEntry(folder, slot, SHAPE, archive_mod.calibration_id(CALIBRATION), CALIBRATION))
            assert i in range(1, 25)
    ds = xr.open_zarr(path)
    assert ds.sizes["run"] == 25 and list(ds["run"].values) == list(range(25))
    for k, folder in enumerate(map(str, ds["folder"].values)):
        i = int(folder.rsplit("/", 1)[1])
        np.testing.assert_array_equal(ds["irradiance"].isel(run=k).values, archive_run(i).channels["irradiance"])
        assert json.loads(str(ds["header"].values[k]))["i"] == i


def test_a_slot_whose_run_never_comes_is_filled(tmp_path, monkeypatch):
    """A writer that took a slot and died (its task re-run elsewhere, landing at another slot):
    the runs after it wait only until that is known, then the last finished run fills the hole;
    a writer that comes back to its old slot afterwards cannot overwrite the run there."""
    path = tmp_path / "a.zarr"
    store = Archive(path)
    store.commit(archive_run(0))
    with store.writer() as session:
        target = session.target
        dead = write_run(target, archive_run(1))  # slot 1 ... its worker dies before reporting
        assert dead is not None and dead.slot == 1
        (path / "sigma" / "1.0.0").unlink()  # ... half-way through its files
        entries = [write_run(target, archive_run(i)) for i in (2, 3)]  # slots 2, 3
        for e in entries:
            session.add(e)
        assert session.commit() == {}  # waiting for slot 1
        assert xr.open_zarr(path).sizes["run"] == 1
        retry = write_run(target, archive_run(1))  # the re-run of run 1: slot 4
        session.add(retry)
        # slot 1's run landed at slot 4: the hole is filled with it
        assert session.commit() == {"/runs/001": 1, "/runs/002": 2, "/runs/003": 3}
        ds = xr.open_zarr(path)
        assert ds.sizes["run"] == 4
        by_folder = {str(f): k for k, f in enumerate(ds["folder"].values)}
        assert sorted(by_folder) == ["/runs/000", "/runs/001", "/runs/002", "/runs/003"]
        for folder, k in by_folder.items():
            i = int(folder.rsplit("/", 1)[1])
            for name in ("irradiance", "sigma"):
                np.testing.assert_array_equal(ds[name].isel(run=k).values, archive_run(i).channels[name])
        assert list(ds["run"].values) == [0, 1, 2, 3]
        # the dead writer comes back and writes slot 1 again: refused, the run there stays
        # private on purpose: the dead writer is made to take slot 1 again, as no public call can
        monkeypatch.setattr(archive_mod, "_reserve", lambda target, folder: 1)
        with pytest.raises(FileExistsError):
            write_run(target, archive_run(1, seed=77))
    ds = xr.open_zarr(path)
    k = list(map(str, ds["folder"].values)).index("/runs/001")
    np.testing.assert_array_equal(ds["irradiance"].isel(run=k).values, archive_run(1).channels["irradiance"])
    assert {zarrv2.chunk_index(p.name) for p in (path / "sigma").iterdir()} - {None} == {0, 1, 2, 3}


def test_failures_recorded_until_the_run_lands(tmp_path):
    path = tmp_path / "a.zarr"
    store = Archive(path)
    store.record_failure("/runs/001", "InputError: truncated raw file")
    assert store.folders() == {} and store.failed()["/runs/001"]["error"] == "InputError: truncated raw file"
    assert xr.open_zarr(path).sizes["run"] == 0
    store.commit(archive_run(0))
    store.record_failure("/runs/002", "boom")
    assert set(store.failed()) == {"/runs/001", "/runs/002"}
    store.commit(archive_run(1))
    assert set(store.failed()) == {"/runs/002"}
    assert json.loads(xr.open_zarr(path).attrs["hdrcap_failed_runs"]).keys() == {"/runs/002"}


@pytest.mark.skipif(
    not os.environ.get("HDRCAP_ZARR2_PYTHON"),
    reason="set HDRCAP_ZARR2_PYTHON to a Python with zarr-python 2 (and xarray) to check that it reads the archive",
)
def test_zarr_python_2_reads_the_archive(tmp_path):
    """zarr-python 2 (consolidated and per-array metadata) and xarray on it read the archive's
    runs as written. zarr-python 2 and 3 do not install side by side: this runs in the Python
    that HDRCAP_ZARR2_PYTHON names (e.g. a venv with ``pip install 'zarr<3' 'xarray<2025' dask``)."""
    import subprocess

    path = tmp_path / "a.zarr"
    runs = [archive_run(i) for i in range(3)]
    Archive(path).commit_many(runs)
    expected = tmp_path / "expected.npz"
    np.savez(
        expected,
        **{name: np.stack([r.channels[name] for r in runs]) for name in CHANNELS},
        folder=np.array([r.folder for r in runs]),
    )
    script = f"""
import numpy as np, xarray as xr, zarr
assert zarr.__version__.startswith("2."), zarr.__version__
want = np.load({str(expected)!r})
for group in (zarr.open_consolidated({str(path)!r}, mode="r"), zarr.open_group({str(path)!r}, mode="r")):
    for name in {list(CHANNELS)!r}:
        assert np.array_equal(group[name][:], want[name], equal_nan=True), name
    assert list(group["folder"][:]) == list(want["folder"])
ds = xr.open_zarr({str(path)!r})
assert np.array_equal(ds["sigma"].values, want["sigma"]) and list(map(str, ds["folder"].values)) == list(want["folder"])
print("ok", zarr.__version__)
"""
    proc = subprocess.run([os.environ["HDRCAP_ZARR2_PYTHON"], "-c", script], capture_output=True, text=True)
    assert proc.returncode == 0 and proc.stdout.startswith("ok 2."), proc.stderr
