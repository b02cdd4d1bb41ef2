"""The inference runner: a steady, safe, traced loop from sensors to the robot."""

from openral_runner.base import InferenceRunnerBase
from openral_runner.clock import Clock, SystemClock, precise_sleep, sleep_until
from openral_runner.hardware import HardwareRunner
from openral_runner.protocol import InferenceRunner
from openral_runner.safety import NullSafetyClient, SafetyClient
from openral_runner.sensor_reader import SensorReader

__all__ = [
    "Clock",
    "HardwareRunner",
    "InferenceRunner",
    "InferenceRunnerBase",
    "NullSafetyClient",
    "SafetyClient",
    "SensorReader",
    "SystemClock",
    "precise_sleep",
    "sleep_until",
]
