"""A third party extends openral exactly as the built-ins do: a separate installed distribution.

The test writes a package and its ``.dist-info`` (entry points) to a temporary folder, puts it on
``PYTHONPATH`` and runs ``openral validate`` and ``openral deploy`` on a deployment that uses only
its plugins: a robot manifest, a camera backend, a skill, a safety client, a tick observer and an
event detector run by the built-in ``perception`` observer. The same tick observer watches a
simulated scene's episodes under ``openral sim run``. Nothing in this repository names any of them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

PACKAGE = '''
"""acme_openral: plugins for openral from outside its repository."""

import json
import threading
from pathlib import Path

from pydantic import BaseModel

from openral_core import Action, FrameEncoding, ROSConfigError, SafetyEnvelope, SensorFrame
from openral_core.skills import RSkillInfo
from openral_observability.observer import TickObserver
from openral_rskill.base import RSkillBase
from openral_runner import LatestFrameSlot, SafetyClient, SlotReader

MANIFEST = str(Path(__file__).with_name("acme_arm.yaml"))


class AcmeCamera(SlotReader):
    """Publishes a flat grey frame of ``shade`` every 5 ms from its own thread."""

    def __init__(self, sensor_id, shade, width, height):
        self.sensor_id = sensor_id
        self._slot = LatestFrameSlot(sensor_id, default_max_age_ms=500.0)
        self._pixels = bytes([shade]) * (width * height * 3)
        self._size = (width, height)
        self._stop = threading.Event()
        self._thread = None

    @classmethod
    def from_config(cls, config, *, hal, robot, base_dir=None):
        return cls(config.sensor_id, int(config.backend_params["shade"]), config.width, config.height)

    def open(self):
        self._slot.open()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def close(self):
        self._stop_worker(self._stop, self._thread, timeout_s=2.0)

    def _run(self):
        import time

        seq = 0
        while not self._stop.wait(0.005):
            seq += 1
            self._slot.publish(
                SensorFrame(sensor_id=self.sensor_id, stamp_ns=time.monotonic_ns(), width=self._size[0],
                            height=self._size[1], encoding=FrameEncoding.BGR8, seq=seq, data=self._pixels)
            )


class AcmeSkill(RSkillBase):
    """Commands every joint to 0.4 rad."""

    def __init__(self, robot):
        super().__init__()
        self._names = robot.joint_names

    @classmethod
    def from_config(cls, params, *, robot, rate_hz):
        return cls(robot)

    @property
    def info(self):
        return RSkillInfo(skill_id="acme", license="MIT")

    def _step_impl(self, world_state):
        return Action(joint_names=self._names, targets=[[0.4] * len(self._names)])


class AcmeSafety(SafetyClient):
    """Halves every target (a very cautious clamp)."""

    envelope = SafetyEnvelope()

    @classmethod
    def from_config(cls, config, *, robot, rate_hz):
        return cls()

    def check_action(self, action):
        return action.model_copy(update={"targets": [[v / 2 for v in row] for row in action.targets]})


class AcmeShadeDetector:
    """Reports the mean grey level of every frame it is shown, and writes the events it made on request."""

    kind = "acme_shade"

    def __init__(self, log):
        self.log = Path(log)

    @classmethod
    def from_config(cls, params, *, base_dir=None):
        extra = sorted(set(params) - {"log"})
        if extra:
            raise ROSConfigError(f"unknown key {extra[0]!r}; allowed keys: log", field=extra[0])
        return cls(params["log"])

    def detect(self, frame):
        grey = float(frame.grey.mean())
        seen = {"sensor": frame.sensor_id, "grey": grey, "size": [frame.width, frame.height]}
        with self.log.open("a") as out:
            out.write(json.dumps(seen) + "\\n")
        return AcmeShade(level=grey)

    def summarise(self, metadata):
        return f"grey {metadata.level:.0f}"


class AcmeShade(BaseModel):
    level: float


class AcmeRecorder(TickObserver):
    """Keeps what each tick sent and the grey level the skill saw; writes it, and the loop it watched, on close."""

    def __init__(self, path, context):
        self.path = Path(path)
        self.context = context
        self.rows = []

    @classmethod
    def from_config(cls, params, context):
        return cls(context.base_dir / params["path"], context)

    def on_tick(self, tick, world):
        frames = world.image_frames if world is not None else None
        grey = None if not frames else float(next(iter(frames.values())).as_array().mean())
        self.rows.append({"sent": tick.sent_action, "requested": tick.requested_action, "grey": grey})

    def close(self):
        loop = {"robot": self.context.robot_id, "rate_hz": self.context.rate_hz,
                "joints": list(self.context.joint_names), "cameras": [list(c) for c in self.context.cameras]}
        self.path.write_text(json.dumps({"loop": loop, "rows": self.rows}))
'''

ENTRY_POINTS = """
[openral.robots]
acme_arm = acme_openral:MANIFEST

[openral.sensor_backends]
acme_cam = acme_openral:AcmeCamera

[openral.skills]
acme = acme_openral:AcmeSkill

[openral.safety_clients]
acme_halver = acme_openral:AcmeSafety

[openral.observers]
acme_recorder = acme_openral:AcmeRecorder

[openral.detectors]
acme_shade = acme_openral:AcmeShadeDetector
"""

ROBOT = """
robot_id: acme_arm
name: ACME two-joint arm
joints:
  - {name: lift, lower: -1.0, upper: 1.0, velocity_limit: 100.0}
  - {name: grip, kind: gripper, lower: 0.0, upper: 1.0, velocity_limit: 100.0}
"""

DEPLOYMENT = """
name: acme_demo
rate_hz: 50
hal: {{robot_id: acme_arm, adapter: null}}
vla: {{id: acme}}
sensors:
  - {{sensor_id: eye, backend: acme_cam, width: 4, height: 2, max_age_ms: 500, backend_params: {{shade: 77}}}}
safety: {{client: acme_halver}}
observers:
  - {{id: acme_recorder, params: {{path: {record}}}}}
  - id: perception
    params:
      rate_hz: 1000
      detectors: [{{kind: acme_shade, params: {{log: {shades}}}}}]
"""


@pytest.fixture
def site(tmp_path: Path) -> Path:
    """A folder holding the installed distribution ``acme-openral`` (package + dist-info)."""
    root = tmp_path / "site"
    package = root / "acme_openral"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text(PACKAGE)
    (package / "acme_arm.yaml").write_text(ROBOT)
    info = root / "acme_openral-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: acme-openral\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(ENTRY_POINTS)
    return root


def _openral(site: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")]))}
    return subprocess.run(
        [sys.executable, "-m", "openral_cli", *args], capture_output=True, text=True, timeout=120, env=env, check=False
    )


def test_a_separate_distribution_plugs_in_every_door(site: Path, tmp_path: Path) -> None:
    record = tmp_path / "ticks.json"
    deployment = tmp_path / "acme.yaml"
    shades = tmp_path / "shades.jsonl"
    deployment.write_text(DEPLOYMENT.format(record=record, shades=shades))

    checked = _openral(site, "validate", str(deployment))
    assert checked.returncode == 0, checked.stderr
    assert "robot acme_arm" in checked.stdout

    ran = _openral(site, "deploy", "--config", str(deployment), "--max-ticks", "20", "--json")
    assert ran.returncode == 0, ran.stderr
    result = json.loads(ran.stdout)
    assert result["n_ticks"] == 20
    assert result["withheld_actions"] == 0
    written = json.loads(record.read_text())
    assert written["loop"] == {
        "robot": "acme_arm",
        "rate_hz": 50.0,
        "joints": ["lift", "grip"],
        "cameras": [["eye", 4, 2]],
    }
    rows = written["rows"]
    assert len(rows) == 20, "the observer saw every tick and was closed"
    assert all(r["requested"] == [0.4, 0.4] for r in rows), "the skill's actions"
    assert all(r["sent"] == [0.2, 0.2] for r in rows), "what the safety client let through"
    assert all(r["grey"] == 77 for r in rows), "the camera's pixels reached the skill's world state"
    seen = [json.loads(line) for line in shades.read_text().splitlines()]
    assert seen, "the perception observer ran the plugin's detector"
    assert all(s == {"sensor": "eye", "grey": 77.0, "size": [4, 2]} for s in seen), seen


SCENE = """
name: acme_reach
env: mock
env_id: reach
task: reach the target
max_steps: 15
n_episodes: 2
cameras: [{{name: top, width: 16, height: 8}}]
observers:
  - {{id: acme_recorder, params: {{path: {record}}}}}
"""


def test_the_third_party_observer_watches_a_simulated_scene_too(site: Path, tmp_path: Path) -> None:
    scene = tmp_path / "scene.yaml"
    scene.write_text(SCENE.format(record="ticks.json"))  # relative: to the scene file's folder
    ran = _openral(site, "sim", "run", "--config", str(scene), "--skill", "mock_reach_expert", "--json")
    assert ran.returncode == 0, ran.stderr
    report = json.loads(ran.stdout)
    written = json.loads((tmp_path / "ticks.json").read_text())
    loop = written["loop"]
    assert (loop["robot"], loop["joints"], loop["cameras"]) == ("reach", ["x", "y"], [["top", 16, 8]])
    assert loop["rate_hz"] > 0, "the env's control rate"
    steps = [r for r in written["rows"] if r["requested"] is not None]
    assert len(steps) == sum(e["steps"] for e in report["episodes"]), "the observer saw every step and was closed"
    assert all(r["grey"] is not None for r in steps), "the rendered camera reached the observer"


def test_a_plugins_detector_validates_its_own_params_and_an_unknown_kind_lists_the_plugins(
    site: Path, tmp_path: Path
) -> None:
    text = DEPLOYMENT.format(record=tmp_path / "ticks.json", shades=tmp_path / "shades.jsonl")
    deployment = tmp_path / "acme.yaml"
    deployment.write_text(text.replace("{log:", "{lgo:"))
    checked = _openral(site, "validate", str(deployment))
    assert checked.returncode == 2
    assert "observers[].params.detectors[0].params.lgo: unknown key 'lgo'" in checked.stderr
    deployment.write_text(text.replace("kind: acme_shade", "kind: acme_shades"))
    checked = _openral(site, "validate", str(deployment))
    assert checked.returncode == 2
    assert "unknown detector 'acme_shades'" in checked.stderr
    assert "acme_shade, motion, objects, scene_change" in checked.stderr


def test_without_the_distribution_the_names_are_unknown_and_listed(tmp_path: Path) -> None:
    deployment = tmp_path / "acme.yaml"
    deployment.write_text(DEPLOYMENT.format(record=tmp_path / "ticks.json", shades=tmp_path / "shades.jsonl"))
    checked = _openral(tmp_path / "empty", "validate", str(deployment))
    assert checked.returncode == 2
    assert "error: hal.robot_id: unknown robot 'acme_arm'" in checked.stderr
    assert "so101_follower" in checked.stderr
