"""Worked example: re-merge a whole run archive on a SLURM cluster with dask-jobqueue.

Not run by the tests (it needs a SLURM cluster). Run it on the login node, inside the
environment hdrcap is installed in (the worker jobs must see the same environment and the
same shared file system: the run folders, the calibration and the archive)::

    pip install dask-jobqueue
    python docs/batch_slurm.py /lab/runs/2026-* --calibration /lab/cam.cal -o /lab/archive.zarr

Each SLURM job starts one Dask worker process with one core; SLURM_JOBS jobs run at once.
The merge of each run happens on a worker, which reads its raw frames from the shared file
system; only the merged arrays come back to this script, which commits them to the archive.
Re-running the script resumes: runs already in the archive are skipped.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run folders or folders of raw brackets")
    ap.add_argument("--calibration", required=True, help="calibration file (from hdrcap calibrate)")
    ap.add_argument("-o", "--output", required=True, type=Path, help="the zarr archive")
    ap.add_argument("--jobs", type=int, default=32, help="SLURM jobs (one worker each)")
    ap.add_argument("--queue", default="compute")
    ap.add_argument("--account", default=None)
    args = ap.parse_args()

    from dask_jobqueue import SLURMCluster

    from hdrcap.batch.driver import BatchSettings, calibration_identity, run_batch

    cluster = SLURMCluster(
        queue=args.queue,
        account=args.account,
        cores=1,  # one worker process with one thread per job: one run at a time
        processes=1,
        memory="4GB",  # a 24 Mpixel bracket of 6 frames merges in well under 2 GB
        walltime="02:00:00",
        job_script_prologue=["export NUMBA_NUM_THREADS=1"],  # the merge kernel's threads: the job's one core
    )
    print(cluster.job_script())
    cluster.scale(jobs=args.jobs)
    settings = BatchSettings(
        calibration=args.calibration,
        camera=None,
        # the defaults of `hdrcap merge` (BatchSettings' default MergeOptions)
        calibration_id=calibration_identity(args.calibration, None),
    )
    try:
        report = run_batch(args.runs, args.output, settings, scheduler=cluster.scheduler_address, progress=True)
    finally:
        cluster.close()
    print(json.dumps(report.to_dict()))


if __name__ == "__main__":
    main()
