"""The simulated sensor (physics) and the simulated camera backend."""

from hdrcap.mock_camera.sensor import PRESETS, SensorSpec, SimulatedSensor, preset

__all__ = ["PRESETS", "SensorSpec", "SimulatedSensor", "preset"]
