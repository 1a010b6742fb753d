"""``hdrcap batch`` on local workers and dask.distributed: every run of the archive bit-identical
to ``hdrcap merge`` of that run, a corrupt run recorded while the others land, resume, a killed
worker loses nothing, and a time series of one photosite with its sigma against the simulator's
truth."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from hdrcap.cli import main as cli_main
from hdrcap.mock_camera.simulation import simulate_bracket
from hdrcap.pipeline.io.exr import read_exr

pytestmark = pytest.mark.slow

CAMERA = "camera-A"
TIMES = [0.001, 0.01, 0.1]


def _bracket(folder: Path, seed: int) -> Path:
    """A simulated bracket with matching dark frames: the same scene, a new noise draw per seed."""
    simulate_bracket(CAMERA, "hdr", TIMES, folder, True, (48, 64), 4.0, 2e5, seed, None, False, progress=False)
    return folder


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    good = [_bracket(root / f"b{i}", seed=10 + i) for i in range(3)]
    cap = root / "cap"  # a capture run folder with its manifest
    assert (
        cli_main(
            [
                "capture",
                "--camera",
                f"mock:{CAMERA}",
                "--times",
                *map(str, TIMES),
                "--out",
                str(cap),
                "--size",
                "64x48",
                "--seed",
                "7",
                "--no-progress",
            ]
        )
        == 0
    )
    planned = root / "planned"  # a capture run the planner planned (per-exposure dark strategies, options)
    assert (
        cli_main(
            [
                "capture",
                "--camera",
                "mock:camera-B",
                "--target-snr",
                "20",
                "--out",
                str(planned),
                "--size",
                "64x48",
                "--seed",
                "8",
                "--no-progress",
            ]
        )
        == 0
    )
    bad = _bracket(root / "bad", seed=99)
    frame = sorted(bad.glob("frame_*.dng"))[1]
    frame.write_bytes(frame.read_bytes()[: frame.stat().st_size // 3])  # truncated raw file
    return {"good": good, "capture": cap, "planned": planned, "bad": bad}


def _merge_exr(tmp: Path, name: str, frames, darks, *extra) -> Path:
    out = tmp / f"{name}.exr"
    assert (
        cli_main(["merge", *map(str, frames), "--darks", *map(str, darks), "--camera", CAMERA, "-o", str(out), *extra])
        == 0
    )
    return out


def test_batch_cli_identical_to_merge_records_failure_and_resumes(runs, tmp_path, cli):
    archive = tmp_path / "a.zarr"
    folders = [*runs["good"], runs["capture"], runs["bad"]]
    proc = cli("batch", *folders, "--camera", CAMERA, "-o", archive, "--workers", "2", "--json")
    assert proc.returncode == 1, proc.stderr  # one run failed: non-zero status, the others landed
    report = json.loads(proc.stdout)
    assert report["committed"] == 4 and list(report["failed"]) == [str(runs["bad"].resolve())]
    assert "Traceback" not in proc.stderr and "run failed" in proc.stderr
    ds = xr.open_zarr(archive)
    by_folder = {str(f): i for i, f in enumerate(ds["folder"].values)}
    assert sorted(by_folder) == sorted(str(f.resolve()) for f in folders[:4])  # each run exactly once
    assert str(runs["bad"].resolve()) in json.loads(ds.attrs["hdrcap_failed_runs"])
    # Every run is bit-identical to `hdrcap merge` of that run, arrays and header (via `hdrcap export`).
    for k, folder in enumerate(folders[:4]):
        folder = folder.resolve()
        if folder == runs["capture"].resolve():
            frames, darks = sorted(folder.glob("frames/*_light_*.dng")), sorted(folder.glob("frames/*_dark_*.dng"))
            ref = read_exr(_merge_exr(tmp_path, f"m{k}", frames, darks, "--dark-strategy", "matched"))
        else:
            ref = read_exr(
                _merge_exr(tmp_path, f"m{k}", sorted(folder.glob("frame_*.dng")), sorted(folder.glob("dark_*.dng")))
            )
        i = by_folder[str(folder)]
        for name, arr in ref.channels.items():
            got = ds[name].isel(run=i).values
            assert got.dtype == arr.dtype and np.array_equal(got, arr, equal_nan=True), (folder, name)
        back = read_exr(_export(archive, i, tmp_path / f"e{k}.exr"))
        assert back.header == ref.header
        assert all(np.array_equal(back.channels[n], ref.channels[n], equal_nan=True) for n in ref.channels)
    # Re-running resumes: the runs there are skipped, only the failed one is tried again.
    proc = cli("batch", *folders, "--camera", CAMERA, "-o", archive, "--workers", "1", "--json")
    report = json.loads(proc.stdout)
    assert proc.returncode == 1 and report["committed"] == 0 and report["skipped"] == 4 and len(report["failed"]) == 1
    assert xr.open_zarr(archive).sizes["run"] == 4


def test_planned_run_follows_its_recorded_plan_as_merge_plan_does(runs, tmp_path):
    from hdrcap.acquire.capture.manifest import Manifest

    folder = runs["planned"].resolve()
    archive = tmp_path / "p.zarr"
    assert (
        cli_main(["batch", str(folder), "--camera", "camera-B", "-o", str(archive), "--workers", "1", "--no-progress"])
        == 0
    )
    plan = Manifest(folder).header()["planning"]["plan"]
    plan_file = tmp_path / "plan.json"
    plan_file.write_text(json.dumps(plan))
    ref = tmp_path / "ref.exr"
    assert (
        cli_main(
            [
                "merge",
                *map(str, sorted(folder.glob("frames/*_light_*.dng"))),
                "--camera",
                "camera-B",
                "--plan",
                str(plan_file),
                "-o",
                str(ref),
            ]
        )
        == 0
    )
    ref, got = read_exr(ref), read_exr(_export(archive, 0, tmp_path / "got.exr"))
    assert (
        got.header["merge"] == ref.header["merge"]
        and got.header["merge"]["saturation"] == plan["merge_options"]["saturation"]
    )
    assert all(np.array_equal(got.channels[n], ref.channels[n], equal_nan=True) for n in ref.channels)
    assert got.header["planner"]["plan_file"] == str(folder / "manifest.jsonl")


def _export(archive: Path, run: int, out: Path) -> Path:
    assert cli_main(["export", str(archive), "--run", str(run), "-o", str(out)]) == 0
    return out


def _kill_when_busy(busy_pid, killed: list[int]) -> None:
    """Kill the process ``busy_pid()`` names (a worker merging a run; None: none yet) as soon as
    it names one, within a minute."""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        pid = busy_pid()
        if pid:
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
            return
        time.sleep(0.01)


def _busy_local_worker(pool) -> int | None:
    """A local worker merging a run (pebble's record of which worker took which task: private,
    pebble is pinned to one major version)."""
    return next((t.worker_id for t in list(pool._pool_manager.task_manager.tasks.values()) if t.worker_id), None)


def _busy_dask_worker(client) -> int | None:
    """The process of a Dask worker merging a run."""
    busy = [w for w, tasks in client.processing().items() if tasks]
    return client.run(os.getpid, workers=[busy[0]])[busy[0]] if busy else None


@pytest.mark.parametrize("where", ["local", "scheduler"])
def test_killed_worker_loses_nothing(runs, tmp_path, where):
    """A worker killed while it merges a run (local pool, or a Dask scheduler's worker): the run
    is merged again by another and lands once, bit-identical; no run fails."""
    from hdrcap.batch.driver import BatchSettings, calibration_identity, run_batch

    archive = tmp_path / "k.zarr"
    settings = BatchSettings(calibration=None, camera=CAMERA, calibration_id=calibration_identity(None, CAMERA))
    killed: list[int] = []
    folders = [*runs["good"], runs["capture"]]
    if where == "local":
        report = run_batch(
            folders,
            archive,
            settings,
            workers=2,
            on_submit=lambda p: _kill_when_busy(lambda: _busy_local_worker(p), killed),
            progress=False,
        )
    else:
        from distributed import LocalCluster

        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
            report = run_batch(
                folders,
                archive,
                settings,
                scheduler=cluster.scheduler_address,
                on_submit=lambda c: _kill_when_busy(lambda: _busy_dask_worker(c), killed),
                progress=False,
            )
    assert killed and not report.failed and len(report.committed) == 4
    ds = xr.open_zarr(archive)
    assert sorted(map(str, ds["folder"].values)) == sorted(str(f.resolve()) for f in folders)  # exactly once
    # ... and the runs are the merge's: the same as a batch without the kill (other test's archive layout).
    from hdrcap.batch.driver import find_runs, merge_run

    for src in find_runs(folders):
        ref = merge_run(src, settings).run
        i = list(map(str, ds["folder"].values)).index(src.folder)
        for name in ("irradiance", "sigma", "nexp"):
            assert np.array_equal(ds[name].isel(run=i).values, ref.channels[name], equal_nan=True)


def test_a_run_whose_worker_always_dies_is_recorded_after_its_attempts(tmp_path):
    """A run that kills its worker process each time (a crash in a library, memory) is given
    again until WORKER_ATTEMPTS tries, then recorded as failed with the worker's exit status;
    the other runs land, and the pool goes on with new workers."""
    from hdrcap.batch.driver import WORKER_ATTEMPTS, RunSource, _local_pool, _pool_batches
    from tests.helpers.tasks import die_on_poison

    todo = [RunSource(f"/runs/{name}", ("f",)) for name in ("a", "poison", "b", "c")]
    with _local_pool(2, 1) as pool:
        finished = [f for batch in _pool_batches(pool, todo, (str(tmp_path),), task=die_on_poison) for f in batch]
    status = {s.folder: (st, r) for s, st, r in finished}
    assert sorted(status) == sorted(s.folder for s in todo)  # each run once
    assert {k: v for k, v in status.items() if k != "/runs/poison"} == {
        f"/runs/{n}": ("finished", f"/runs/{n}") for n in "abc"
    }
    st, (kind, err, _) = status["/runs/poison"]
    assert st == "error" and kind is RuntimeError
    assert str(err) == f"its worker process died (exit code 7) in each of {WORKER_ATTEMPTS} attempts"
    assert len(list(tmp_path.glob("poison-*"))) == WORKER_ATTEMPTS  # one try per attempt, in a worker of its own


def test_a_script_without_a_main_guard_gets_a_one_line_error(runs, tmp_path):
    """Local workers are spawned: each imports the caller's main module. A script that calls
    run_batch at its top level makes every worker end as it starts; the batch says so instead
    of waiting for workers that never come."""
    import subprocess
    import sys

    script = tmp_path / "unguarded.py"
    script.write_text(
        "from hdrcap.batch.driver import BatchSettings, run_batch\n"
        f"run_batch([{str(runs['good'][0])!r}], {str(tmp_path / 'u.zarr')!r}, BatchSettings(None, {CAMERA!r}), "
        "workers=1, progress=False)\n"
    )
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("RuntimeError: the batch's worker processes end as they start")
    assert 'if __name__ == "__main__":' in last


def test_time_series_of_one_photosite_with_sigma(runs, tmp_path, monkeypatch):
    """Three runs of the same scene: the archive's time series of a photosite scatters about the
    simulator's truth as its sigma says. The workers write the runs' arrays: the client writes
    none (it commits metadata), and a run merged again with force is rewritten in place."""
    from hdrcap.batch.archive import ArchiveWriter
    from hdrcap.batch.driver import BatchSettings, calibration_identity, run_batch

    def no_arrays_on_the_client(self, run):
        raise AssertionError("the client wrote a run's arrays")

    monkeypatch.setattr(ArchiveWriter, "write", no_arrays_on_the_client)
    archive = tmp_path / "t.zarr"
    settings = BatchSettings(calibration=None, camera=CAMERA, calibration_id=calibration_identity(None, CAMERA))
    report = run_batch(runs["good"], archive, settings, workers=1, progress=False)
    assert len(report.committed) == 3 and not report.failed and 1 <= report.commits <= 3
    before = xr.open_zarr(archive).load()
    again = run_batch(runs["good"][1:2], archive, settings, workers=1, force=True, progress=False)
    assert again.committed == {str(runs["good"][1].resolve()): report.committed[str(runs["good"][1].resolve())]}
    after = xr.open_zarr(archive).load()
    assert after.identical(before)  # rewritten in place: the same run number, the same bits
    ds = xr.open_zarr(archive).sortby("start_time")
    truth = read_exr(runs["good"][0] / "truth.exr").channels["irradiance"]
    y, x = np.unravel_index(np.argsort(truth, axis=None)[truth.size // 2], truth.shape)  # a mid-range photosite
    series = ds[["irradiance", "sigma", "nexp"]].isel(y=int(y), x=int(x)).compute()
    assert series["irradiance"].dims == ("run",) and series.sizes["run"] == 3
    assert (series["nexp"] > 0).all() and (series["sigma"] > 0).all()
    z = (series["irradiance"] - truth[y, x]) / series["sigma"]
    assert np.all(np.abs(z) < 5)
    # the same per photosite over the frame: normalised errors of unit spread in every run
    ok = (ds["nexp"] > 0).values
    zall = ((ds["irradiance"].values - truth[None]) / ds["sigma"].values)[ok]
    assert 0.85 < zall.std() < 1.15 and abs(zall.mean()) < 0.1


def test_the_slurm_example_runs_with_a_stand_in_for_dask_jobqueue(runs, tmp_path, monkeypatch, capsys):
    """docs/batch_slurm.py, with a local cluster standing in for SLURMCluster (the same
    arguments, checked against dask-jobqueue 0.9): the batch through a scheduler address."""
    import runpy
    import sys
    import types

    from distributed import LocalCluster

    made = {}

    class SLURMCluster:
        def __init__(self, *, queue, account, cores, processes, memory, walltime, job_script_prologue):
            made.update(cores=cores, processes=processes, memory=memory, prologue=job_script_prologue)
            self._local = LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None)
            self.scheduler_address = self._local.scheduler_address

        def job_script(self) -> str:
            return "#!/usr/bin/env bash"

        def scale(self, jobs: int) -> None:
            made["jobs"] = jobs

        def close(self) -> None:
            self._local.close()

    monkeypatch.setitem(sys.modules, "dask_jobqueue", types.SimpleNamespace(SLURMCluster=SLURMCluster))
    from hdrcap.acquire.camera.model import camera_model
    from hdrcap.pipeline.calibration.archive import save_calibration

    archive = tmp_path / "s.zarr"
    calibration = save_calibration(tmp_path / "cam.cal", camera_model(None, CAMERA))  # a calibration file
    script = Path(__file__).resolve().parents[2] / "docs" / "batch_slurm.py"
    folders = [str(f) for f in runs["good"][:2]]
    monkeypatch.setattr(sys, "argv", [str(script), *folders, "--calibration", str(calibration), "-o", str(archive)])
    runpy.run_path(str(script), run_name="__main__")
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["committed"] == 2 and not report["failed"]
    assert made == {"cores": 1, "processes": 1, "memory": "4GB", "jobs": 32, "prologue": made["prologue"]}
    ds = xr.open_zarr(archive)
    assert ds.sizes["run"] == 2
    # the calibration file's identity, parameters and provenance, once, for both runs
    ((cid, record),) = json.loads(ds.attrs["hdrcap_calibrations"]).items()
    assert set(map(str, ds["calibration"].values)) == {cid} and record["file"] == str(calibration.resolve())


def test_a_task_that_raised_is_recorded_with_its_error(tmp_path):
    """What Dask gives for a task that raised (not bad input: any exception), or was cancelled,
    is recorded as the run's failure with a one-line error; the others land."""
    from concurrent.futures import CancelledError

    from hdrcap.batch.archive import Archive
    from hdrcap.batch.driver import BatchReport, RunOutcome, RunSource, _Committer  # private on purpose: fed directly
    from tests.helpers.archive import archive_run

    store = Archive(tmp_path / "e.zarr")
    report = BatchReport(str(store.path))
    with store.writer() as session:
        committer = _Committer(session, report, force=False)
        boom = RuntimeError("boom\nsecond line")
        committer.take(RunSource("/runs/001", ("f",)), "error", (RuntimeError, boom, None))
        committer.take(RunSource("/runs/002", ("f",)), "cancelled", CancelledError("lost"))
        committer.take(RunSource("/runs/000", ("f",)), "finished", RunOutcome(None, archive_run(0), ("w",), 1.0))
        assert committer.commit() == 1
    assert report.failed == {"/runs/001": "RuntimeError: boom", "/runs/002": "CancelledError: lost"}
    assert report.committed == {"/runs/000": 0} and report.warnings == ["/runs/000: w"]
    assert set(store.failed()) == {"/runs/001", "/runs/002"}


def _worker_state() -> tuple[int, bool, int]:
    import sys

    import numba

    time.sleep(0.3)  # long enough for the other worker to take the next one
    return os.getpid(), "hdrcap.pipeline.merge.kernels" in sys.modules, numba.get_num_threads()


def test_workers_load_the_merge_kernels_before_their_first_run():
    """The workers' fixed cost (numba and the merge kernels) is paid while the pool starts, by
    every worker at once, not inside the first run of each; each runs the threads asked for."""
    from hdrcap.batch.driver import _local_pool

    with _local_pool(2, 1) as pool:
        states = [pool.schedule(_worker_state) for _ in range(2)]
        got = [f.result(timeout=60) for f in states]
    assert len({pid for pid, _, _ in got}) == 2 and all(loaded and n == 1 for _, loaded, n in got)
