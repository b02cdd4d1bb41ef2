"""The inference runner: a steady, safe, traced loop from sensors to the robot.

What an extender needs is exported here: the seams (``SensorReader``, ``SafetyClient``,
``TickObserver``), the two observer bases (``QueuedObserver`` for every tick in order,
``LatestPerKeyObserver`` for the newest item per camera), the slot a capture backend publishes
into (``LatestFrameSlot``, ``SlotReader``) and ``build_runner``, which turns a deployment into a
running ``HardwareRunner``.
"""

from openral_observability.latest_observer import LatestPerKeyObserver
from openral_observability.observer import TickObserver
from openral_observability.queued_observer import QueuedObserver
from openral_runner.base import InferenceRunnerBase
from openral_runner.clock import Clock, SystemClock, precise_sleep, sleep_until
from openral_runner.factory import build_runner
from openral_runner.frame_slot import LatestFrameSlot, SlotReader
from openral_runner.hardware import HardwareRunner
from openral_runner.protocol import InferenceRunner
from openral_runner.safety import NullSafetyClient, SafetyClient
from openral_runner.sensor_reader import SensorReader, SyncedSensorReader

__all__ = [
    "Clock",
    "HardwareRunner",
    "InferenceRunner",
    "InferenceRunnerBase",
    "LatestFrameSlot",
    "LatestPerKeyObserver",
    "NullSafetyClient",
    "QueuedObserver",
    "SafetyClient",
    "SensorReader",
    "SlotReader",
    "SyncedSensorReader",
    "SystemClock",
    "TickObserver",
    "build_runner",
    "precise_sleep",
    "sleep_until",
]
