"""The optimal merge (Sec. 4-5, Fig. 3): options and accumulator (with its parts: frames and dark
levels, calibration maps, exposure times, weight precision, calibration errors, quality flags),
compiled kernels, which dark level serves an exposure, the baselines of Table 1, and ``files``:
the one path from a bracket of files to a result (in memory or tiled)."""
