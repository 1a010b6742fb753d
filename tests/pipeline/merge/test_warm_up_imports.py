"""The numba warm-up thread of `hdrcap merge` and `hdrcap denoise` (pipeline.merge.files.start_warm_up)
never imports a module while the main thread may import it too.

Two threads importing numba at once meet CPython's per-module import locks: a thread that takes
``numba.core`` before ``numba`` (``from numba.core import config``) while another runs numba's
``__init__`` (which takes them the other way round) trips the deadlock detector
(``_DeadlockError``, CPython gh-83065), or a thread is handed a half-initialised module; and an
import of numba that fails half-way leaves ``numba.core`` in ``sys.modules``, so that the next
``import numba`` builds a module without its ``core`` attribute (``AttributeError: module 'numba'
has no attribute 'core'``, exit 70). Which thread gets there first depends on the machine's load
and disk; the processes below force the orders a loaded machine produces, by slowing down the
modules' loading (as a cold disk does), each in a fresh process with an empty kernel cache.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

#: One process: slow imports (module:thread-prefix:seconds, ``create`` slows the creation of the
#: module object, after its lock is taken and before it is in sys.modules), then what
#: ``hdrcap merge`` does: the warm-up thread, the main thread's own numba imports
#: (``MergeAccumulator.result``), the kernels; reports what went wrong in either thread.
DRIVER = r"""
import importlib.abc, json, sys, threading, time, traceback

slow = [item.split(":") for item in sys.argv[1].split(",") if item]


class Slow(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        thread = threading.current_thread().name
        for item in list(slow):
            where, mod, prefix, seconds = item if len(item) == 4 else ["exec", *item]
            if mod != name or not thread.startswith(prefix):
                continue
            slow.remove(item)
            spec = next(s for f in sys.meta_path[1:] if (s := f.find_spec(name, path, target)) is not None)
            method = "create_module" if where == "create" else "exec_module"
            real = getattr(spec.loader, method)

            def delayed(arg, real=real, seconds=float(seconds)):
                time.sleep(seconds)
                return real(arg)

            setattr(spec.loader, method, delayed)
            return spec
        return None


sys.meta_path.insert(0, Slow())
problems = []
import hdrcap.pipeline.merge.files as files


def recorded(work):  # the warm-up's own failures are swallowed by the command: record them here
    try:
        if work is None:  # before the fix the thread imported numba and the kernels itself
            from hdrcap.pipeline._numba_target import warm_up
            from hdrcap.pipeline.merge import kernels  # noqa: F401

            work = warm_up
        work()
    except BaseException as err:
        problems.append(f"warm-up thread: {type(err).__name__}: {err}")


files._warm_up = recorded
from hdrcap.pipeline.merge.files import start_warm_up

thread = start_warm_up()
try:
    import numba  # as MergeAccumulator.result does

    from hdrcap.pipeline.merge.kernels import FrameTable  # noqa: F401

    assert sys.modules["numba"] is numba, "two numba modules"
    numba.get_num_threads()
    numba.core.registry.cpu_target.target_context
    numba.core.entrypoints.init_all()
except BaseException as err:
    problems.append(f"main thread: {type(err).__name__}: {err}")
thread.join(timeout=120)
print(json.dumps(problems))
"""

#: Orders of a loaded machine: the main thread creates numba's module while the warm-up thread
#: still loads llvmlite (its first import), with different overlaps.
ORDERS = [
    "create:numba:MainThread:1.0,llvmlite.binding:hdrcap-kernel:0.2",
    "create:numba:MainThread:1.5,llvmlite.binding:hdrcap-kernel:0.4",
    "create:numba:MainThread:0.8,llvmlite.binding:hdrcap-kernel:0.1",
    "create:numba:MainThread:2.0,llvmlite.binding:hdrcap-kernel:0.8",
    "numba.core:hdrcap-kernel:0.5",
    "",
]


def test_the_warm_up_thread_imports_nothing_the_main_thread_imports(tmp_path):
    procs = []
    for k, order in enumerate(ORDERS):
        cache = tmp_path / f"cache{k}"
        cache.mkdir()  # a cold kernel cache: nothing loaded, nothing compiled before the imports race
        env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
        procs.append(
            subprocess.Popen(
                [sys.executable, "-c", DRIVER, order],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                env=env,
                text=True,
            )
        )
    failed = {}
    for order, proc in zip(ORDERS, procs):
        out, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err
        problems = json.loads(out.strip().splitlines()[-1])
        if problems:
            failed[order or "(no delay)"] = problems
    assert failed == {}
