"""The paper's experiments on the simulator: Sec. 7 (SNR of every weighting against the bound,
Figs. 2, 4, 5, 6) and Sec. 9 (Fig. 8d, uncertainty-driven denoising).

This package sits above :mod:`hdrcap.pipeline` and :mod:`hdrcap.mock_camera`: it draws frames
from the simulator, runs the pipeline's numerics on them and writes JSON and PNG files. Nothing
below it imports it; ``hdrcap evaluate`` is its command line.

* :mod:`.snr`: the Sec. 7 Monte-Carlo driver (setups, merges, SNR and Q-Q experiments, the run).
* :mod:`.denoising`: the Fig. 8d experiment.
* :mod:`.figures`: their figures.
"""

from hdrcap.experiments.denoising import (
    CONTROL_SCENES,
    EVAL_SCENES,
    EVAL_TIMES,
    evaluate_denoising,
    simulate_merged_scene,
)
from hdrcap.experiments.snr import (
    BASELINES,
    CURVES,
    OPTIMAL_OPTIONS,
    TEN_X_READOUT,
    ZERO_READOUT,
    EvalSetup,
    evaluation_params,
    make_setup,
    merge_method,
    qq_experiment,
    run_evaluation,
    simulate_bracket_arrays,
    snr_experiment,
    summarise,
)

__all__ = [
    "BASELINES",
    "CURVES",
    "OPTIMAL_OPTIONS",
    "TEN_X_READOUT",
    "ZERO_READOUT",
    "EvalSetup",
    "evaluation_params",
    "make_setup",
    "simulate_bracket_arrays",
    "merge_method",
    "snr_experiment",
    "qq_experiment",
    "run_evaluation",
    "summarise",
    "EVAL_TIMES",
    "EVAL_SCENES",
    "CONTROL_SCENES",
    "simulate_merged_scene",
    "evaluate_denoising",
]
