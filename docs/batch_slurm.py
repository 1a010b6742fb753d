"""Worked example: re-merge a whole run archive on a SLURM cluster with dask-jobqueue.

It needs a SLURM cluster (tests/test_batch.py runs it with a local Dask cluster standing in for
dask-jobqueue's SLURMCluster). Run it on the login node, inside the environment hdrcap is
installed in. The worker jobs must see the same environment (the same hdrcap version) and, at
the same paths, on a shared file system: the run folders, the calibration file (and its dark
library), and the archive's folder (the workers write the runs into it)::

    pip install dask-jobqueue
    python docs/batch_slurm.py /lab/runs/2026-* --calibration /lab/cam.cal -o /lab/archive.zarr --jobs 32

Each SLURM job runs CORES Dask worker processes of one thread each (``NUMBA_NUM_THREADS=1``: the
merge kernel's threads); JOBS jobs run at once. Each worker merges one run at a time: it reads
the raw frames from the shared file system and writes the merged run's chunk files straight
into the archive; this script (the client) only commits the runs' metadata. Re-running the
script resumes: runs already in the archive are skipped, failed ones are tried again.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run folders or folders of raw brackets")
    ap.add_argument("--calibration", required=True, help="calibration file (from hdrcap calibrate)")
    ap.add_argument("-o", "--output", required=True, type=Path, help="the zarr archive (on the shared file system)")
    ap.add_argument("--jobs", type=int, default=32, help="SLURM jobs")
    ap.add_argument("--cores", type=int, default=1, help="cores per job: one single-threaded worker per core")
    ap.add_argument("--memory", default="4GB", help="per job: a 24 Mpixel bracket of 6 frames merges in under 2 GB")
    ap.add_argument("--queue", default="compute")
    ap.add_argument("--account", default=None)
    ap.add_argument("--walltime", default="02:00:00")
    args = ap.parse_args()

    from dask_jobqueue import SLURMCluster

    from hdrcap.batch.driver import BatchSettings, calibration_identity, run_batch

    cluster = SLURMCluster(
        queue=args.queue,
        account=args.account,
        cores=args.cores,  # threads of the job's Dask workers in all ...
        processes=args.cores,  # ... in one worker process per core: one run per core at a time
        memory=args.memory,  # shared by the job's workers
        walltime=args.walltime,
        job_script_prologue=["export NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1"],  # the merge kernel: one core
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
