"""hdrcap: instrument-grade HDR capture for linear raw cameras.

One import name for the whole project. The subpackages follow the layering of the paper's
pipeline (imports point downward only)::

    hdrcap.acquire      camera control, capture sessions, jobs and the command line
    hdrcap.planner      exposure planning and model selection (Sec. 8)
    hdrcap.mock_camera  the simulated sensor and camera (physics only)
    hdrcap.experiments  the paper's Sec. 7 experiments on the simulator
    hdrcap.pipeline     the numerical core: noise model, calibration, merge, denoise, I/O

The public Python API (:mod:`hdrcap.api`) is re-exported here and imported lazily on first
use (PEP 562), so that ``import hdrcap`` stays cheap (it imports neither numpy nor numba)::

    import hdrcap

    sim = hdrcap.simulate("camera-B", times=[0.001, 0.01, 0.1, 1.0], seed=1)
    hdr = hdrcap.merge(sim.frames, sim.times, calibration=sim.calibration)
"""

from __future__ import annotations

TYPE_CHECKING = False  # typing is not imported at run time: `import hdrcap` stays cheap
if TYPE_CHECKING:
    from typing import Any

__version__ = "0.1.0"

__all__ = [
    "HdrResult",
    "HdrcapError",
    "InputError",
    "MergeOptions",
    "Simulation",
    "__version__",
    "calibrate",
    "camera_calibration",
    "denoise",
    "load_calibration",
    "merge",
    "plan",
    "read_exr",
    "save_calibration",
    "simulate",
    "write_exr",
]

#: Names of :mod:`hdrcap.api` available as ``hdrcap.NAME``.
_API = frozenset(__all__) - {"__version__"}


def __getattr__(name: str) -> Any:
    """Import :mod:`hdrcap.api` on first access to one of its names (PEP 562)."""
    if name in _API:
        from hdrcap import api

        value = getattr(api, name)
        globals()[name] = value  # later look-ups skip this function
        return value
    raise AttributeError(f"module 'hdrcap' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
