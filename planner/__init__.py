"""Exposure planning and model selection on top of pipeline's noise model (Sec. 8).

``plan_exposures`` plans the exposures (and dark frames) that reach a target SNR on a scene;
``meter`` estimates the scene's irradiance from one or two quick frames; ``predict_snr``
predicts the merge's SNR for any exposure set. Imports point down: planner -> pipeline.
"""

from hdrcap.planner.ladder import THIRD_STOP_LADDER, parse_time, shutter_ladder
from hdrcap.planner.meter import MeterReport, meter
from hdrcap.planner.plan import Plan, irradiance_histogram, plan_bracket, plan_exhaustive, plan_exposures
from hdrcap.planner.predict import SnrPrediction, SystematicErrors, predict_snr, systematic_errors_from_calibration

__all__ = [
    "Plan",
    "plan_exposures",
    "plan_exhaustive",
    "plan_bracket",
    "irradiance_histogram",
    "meter",
    "MeterReport",
    "predict_snr",
    "SnrPrediction",
    "SystematicErrors",
    "systematic_errors_from_calibration",
    "THIRD_STOP_LADDER",
    "shutter_ladder",
    "parse_time",
]
