"""Sensor benchmark: frame age at read, delivered fps and bytes copied per backend; camera cost on tick jitter.

Per backend (OpenCV reading a paced video file, GStreamer videotestsrc, the twin's MuJoCo
camera), a full runner ticks at 30 Hz with a 30 fps camera and a probe skill that records,
for every tick, the age of the frame it received (from the capture stamp) and whether the
frame's pixels are the very buffer the backend captured (bytes copied between capture and
skill). Then the twin deployment runs with its camera on and off and the tick-start jitter
is compared in the same run.

Run:  uv run python benchmarks/sensors.py [--seconds 6]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from _common import machine_line, run_deployment
from openral_core import Action, RobotEnvironment, RSkillInfo, WorldState
from openral_rskill.base import RSkillBase
from openral_runner.factory import build_runner

ROOT = Path(__file__).resolve().parents[1]
DEPLOYMENTS = ROOT / "deployments"


class ProbeSkill(RSkillBase):
    """Holds the pose and records what each tick's frames cost to get here."""

    def __init__(self, readers: Mapping[str, Any]) -> None:
        super().__init__()
        self.readers = readers
        self.ages_ms: list[float] = []
        self.copied_bytes: list[int] = []
        self.seqs: set[tuple[str, int]] = set()

    @property
    def info(self) -> RSkillInfo:
        return RSkillInfo(skill_id="probe")

    def _step_impl(self, world_state: WorldState) -> Action:
        now = time.monotonic_ns()
        copied = 0
        for sensor_id, frame in (world_state.image_frames or {}).items():
            self.ages_ms.append(frame.age_ms(now))
            self.seqs.add((sensor_id, frame.seq))
            captured = self.readers[sensor_id].read_latest(1e9)
            if captured.seq == frame.seq and not np.shares_memory(frame.as_array(), captured.as_array()):
                copied += frame.as_array().nbytes
        self.copied_bytes.append(copied)
        state = world_state.joint_state
        assert state is not None
        return Action(joint_names=state.names, targets=[list(state.positions)], skill_id="probe")


def _env(sensor: dict[str, Any] | None, *, hal: str = "null", name: str = "bench") -> RobotEnvironment:
    data: dict[str, Any] = {
        "name": name,
        "rate_hz": 30,
        "hal": {"robot_id": "so101_follower", "adapter": hal},
        "vla": {"id": "noop"},
        "safety": {"client": "envelope"},
        "realtime": {"switch_interval_s": 0.001},
        "sensors": [sensor] if sensor else [],
    }
    return RobotEnvironment.model_validate(data)


def measure_backend(label: str, env: RobotEnvironment, seconds: float) -> str:
    runner, skill = build_runner(env, base_dir=DEPLOYMENTS)
    skill.shutdown()
    readers = {r.sensor_id: r for r in runner.sensor_readers}
    probe = ProbeSkill(readers)
    probe.configure()
    probe.activate()
    runner.skill = probe
    runner.activate()
    try:
        time.sleep(1.0)  # let the camera start delivering
        runner.run(duration_s=seconds)
        delivered_fps = {sid: getattr(r, "delivered_fps", float("nan")) for sid, r in readers.items()}
    finally:
        runner.deactivate()
    ages = np.array(probe.ages_ms)
    seen_fps = len(probe.seqs) / seconds
    delivered = float(np.mean(list(delivered_fps.values())))
    return (
        f"{label:<22} frame age ms p50 {np.percentile(ages, 50):6.1f} p99 {np.percentile(ages, 99):6.1f}  "
        f"delivered {delivered:5.1f} fps (distinct frames seen by the skill {seen_fps:5.1f}/s)  "
        f"bytes copied capture→skill per tick {np.mean(probe.copied_bytes):.0f}"
    )


def twin_jitter(seconds: float, *, camera: bool) -> tuple[float, float, float]:
    env = RobotEnvironment.from_yaml(DEPLOYMENTS / ("so101_twin_camera.yaml" if camera else "so101_twin_hello.yaml"))
    result, _runner = run_deployment(env, DEPLOYMENTS, seconds)
    return result.start_jitter_us_p50, result.start_jitter_us_p99, result.tick_ms_p99


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=6.0)
    args = parser.parse_args()
    print(machine_line())
    video = {
        "sensor_id": "front",
        "backend": "opencv_thread",
        "fps": 30,
        "width": 320,
        "height": 240,
        "backend_params": {"device": "media/demo_320x240.mp4", "loop": True, "paced": True},
    }
    testsrc = {
        "sensor_id": "front",
        "backend": "gstreamer",
        "fps": 30,
        "width": 320,
        "height": 240,
        "backend_params": {"source": "testsrc"},
    }
    twin_cam = {
        "sensor_id": "front",
        "backend": "mujoco_camera",
        "fps": 30,
        "width": 320,
        "height": 240,
        "max_age_ms": 150,
        "encoding": "rgb8",
    }
    print(measure_backend("opencv (video file)", _env(video), args.seconds))
    print(measure_backend("gstreamer (testsrc)", _env(testsrc), args.seconds))
    print(measure_backend("twin camera (mujoco)", _env(twin_cam, hal="mujoco_twin"), args.seconds))
    off = twin_jitter(args.seconds, camera=False)
    on = twin_jitter(args.seconds, camera=True)
    print(f"twin tick-start jitter µs, camera off: p50 {off[0]:.1f} p99 {off[1]:.1f} (tick p99 {off[2]:.2f} ms)")
    print(f"twin tick-start jitter µs, camera on:  p50 {on[0]:.1f} p99 {on[1]:.1f} (tick p99 {on[2]:.2f} ms)")
    print(f"camera on / off p99 jitter ratio: {on[1] / max(off[1], 1e-9):.2f}x (target <= 1.5x)")
    print(machine_line())


if __name__ == "__main__":
    main()
