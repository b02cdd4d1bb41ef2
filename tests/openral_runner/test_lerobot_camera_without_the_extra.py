"""Without LeRobot the ``lerobot_camera`` backend still loads; building a sensor with it names the extra."""

from __future__ import annotations

import json
import subprocess
import sys

from tests.conftest import WITHOUT_LEROBOT

BUILD_WITHOUT_LEROBOT = (
    WITHOUT_LEROBOT
    + """
import json

from openral_core import ROSDependencyMissing, SensorReaderConfig
from openral_runner.factory import SENSOR_BACKEND_REGISTRY

backend = SENSOR_BACKEND_REGISTRY.resolve("lerobot_camera", field="backend")
config = SensorReaderConfig(
    sensor_id="cam", backend="lerobot_camera", backend_params={"type": "zmq", "server_address": "127.0.0.1"}
)
try:
    backend.from_config(config, hal=None, robot=None)
except ROSDependencyMissing as exc:
    print(json.dumps([exc.module, exc.extra, str(exc), "lerobot" in sys.modules]))
"""
)


def test_building_a_lerobot_camera_without_lerobot_names_the_extra() -> None:
    proc = subprocess.run(
        [sys.executable, "-c", BUILD_WITHOUT_LEROBOT], capture_output=True, text=True, timeout=60, check=True
    )
    module, extra, message, imported = json.loads(proc.stdout.strip().splitlines()[-1])
    assert (module, extra) == ("lerobot", "lerobot")
    assert "lerobot_camera" in message
    assert imported is False
