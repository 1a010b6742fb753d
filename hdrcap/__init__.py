"""hdrcap: instrument-grade HDR capture for linear raw cameras.

One import name for the whole project. The subpackages follow the layering of the paper's
pipeline (imports point downward only)::

    hdrcap.acquire      camera control, capture sessions, jobs and the command line
    hdrcap.planner      exposure planning and model selection (Sec. 8)
    hdrcap.mock_camera  the simulated sensor and camera (physics only)
    hdrcap.experiments  the paper's Sec. 7 experiments on the simulator
    hdrcap.pipeline     the numerical core: noise model, calibration, merge, denoise, I/O

The public Python API (:mod:`hdrcap.api`) is re-exported here and imported lazily, so that
``import hdrcap`` stays cheap.
"""

from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["__version__"]
