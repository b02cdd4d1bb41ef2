"""Recording benchmark: what recording a LeRobotDataset costs the loop, recording off vs on, in one run.

The same hardware runner (null HAL with the SO-101 joints, hold skill, null safety client) runs at
30 Hz with two synthetic 640x480 cameras capturing at 30 fps on their own threads (moving
gradients plus noise, so the encoder has real work). It runs ``--seconds`` without recording, then
the same time recording ``--episodes`` equal episodes back to back (a new episode starts as soon
as the last one is closed). Reported:

* tick time p50/p99 and missed slots, off and on; the p50 difference is the time recording adds
  to the tick thread (handing references to the recorder's queue, plus contention from the
  encoder threads);
* the time to close each episode (``episode_end`` to committed, measured on the recorder's
  worker: finishing both videos, writing the tables, renaming into place);
* resident memory after each episode (flat means nothing accumulates across episodes);
* repeated video frames (an encoder fell behind) and dropped ticks (the recorder's queue overflowed).

Run:  uv run python benchmarks/recording.py [--seconds 60] [--episodes 10] [--vcodec libsvtav1]
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from _common import machine_line
from openral_core import FrameEncoding, RealtimeConfig, RunResult, SensorReaderConfig
from openral_dataset.recorder import RolloutRecorder
from openral_dataset.schema import CameraSpec
from openral_dataset.writer import LeRobotDatasetSink
from openral_hal.manifests import load_robot_manifest
from openral_hal.null import NullHAL
from openral_rskill.noop import HoldSkill
from openral_runner.frame_slot import LatestFrameSlot, SlotReader, frame_from_array
from openral_runner.hardware import HardwareRunner
from openral_runner.safety import NullSafetyClient
from openral_world_state import WorldStateAggregator

W, H, FPS = 640, 480, 30


class SyntheticCamera(SlotReader):
    """Captures moving 640x480 pictures at 30 fps on a thread (frames made ahead: capture costs a copy)."""

    def __init__(self, sensor_id: str, seed: int) -> None:
        self.sensor_id = sensor_id
        self._slot = LatestFrameSlot(sensor_id, default_max_age_ms=200.0)
        rng = np.random.default_rng(seed)
        x = np.linspace(0, 255, W, dtype=np.float32)[None, :, None]
        y = np.linspace(0, 255, H, dtype=np.float32)[:, None, None]
        base = (x + y) / 2 + rng.normal(0, 12, (H, W, 3)).astype(np.float32)
        self._frames = [np.clip(np.roll(base, 8 * i, axis=1), 0, 255).astype(np.uint8) for i in range(64)]
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def open(self) -> None:
        self._slot.open()
        self._stop.clear()
        self._thread = threading.Thread(target=self._capture, name=f"camera-{self.sensor_id}", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop_worker(self._stop, self._thread, timeout_s=2.0)

    def _capture(self) -> None:
        period = 1.0 / FPS
        start = time.perf_counter()
        seq = 0
        while not self._stop.is_set():
            pixels = self._frames[seq % len(self._frames)].copy()  # a camera hands over a new buffer
            self._slot.publish(
                frame_from_array(
                    self.sensor_id, pixels, stamp_ns=time.monotonic_ns(), seq=seq, encoding=FrameEncoding.RGB8
                )
            )
            seq += 1
            self._stop.wait(max(0.0, start + seq * period - time.perf_counter()))


def _runner(recorder: RolloutRecorder | None, realtime: RealtimeConfig) -> HardwareRunner:
    robot = load_robot_manifest("so101_follower")
    skill = HoldSkill(robot)
    skill.configure()
    skill.activate()
    sensors = [SensorReaderConfig(sensor_id=cam, max_age_ms=200.0) for cam in ("front", "wrist")]
    return HardwareRunner(
        hal=NullHAL(robot, {}),
        skill=skill,
        aggregator=WorldStateAggregator(joint_max_age_ms=1000.0, sensors=sensors),
        sensor_readers=[SyntheticCamera("front", 1), SyntheticCamera("wrist", 2)],
        safety_client=NullSafetyClient(),
        rate_hz=FPS,
        thumbnail_hz=0.0,
        recorder=recorder,
        realtime=realtime,
    )


def _rss_mb() -> float:
    """Resident memory now (``/proc``), in MB."""
    with open("/proc/self/statm", encoding="ascii") as statm:
        return int(statm.read().split()[1]) * resource.getpagesize() / 2**20


def _line(label: str, results: list[RunResult]) -> str:
    p50 = float(np.median([r.tick_ms_p50 for r in results]))
    p99 = max(r.tick_ms_p99 for r in results)
    missed = sum(r.missed_slots for r in results)
    ticks = sum(r.n_ticks for r in results)
    return f"{label:<4} ticks {ticks:>6}  tick p50 {p50 * 1e3:7.1f} µs  p99 {p99 * 1e3:8.1f} µs  missed slots {missed}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=60.0, help="run time with recording off, and again on")
    parser.add_argument("--episodes", type=int, default=10, help="episodes the recorded time is split into")
    parser.add_argument("--vcodec", default="libsvtav1", choices=["libsvtav1", "h264"])
    parser.add_argument(
        "--sched-fifo",
        type=int,
        default=50,
        help="SCHED_FIFO priority of the tick thread, as the example deployments set it (0: leave the policy)",
    )
    args = parser.parse_args()
    # The example deployments' real-time settings (a warning, not a failure, where not permitted).
    realtime = RealtimeConfig(switch_interval_s=0.001, sched_fifo_priority=args.sched_fifo or None)
    print(machine_line())
    print(f"real-time settings: {realtime.model_dump(exclude_defaults=True)}")

    runner = _runner(None, realtime)
    runner.activate()
    try:
        off = [runner.run(duration_s=args.seconds)]
    finally:
        runner.deactivate()

    with tempfile.TemporaryDirectory(prefix="openral-bench-") as tmp:
        robot = load_robot_manifest("so101_follower")
        sink = LeRobotDatasetSink(
            Path(tmp) / "ds",
            fps=FPS,
            robot_type=robot.robot_id,
            joint_names=robot.joint_names,
            cameras=[CameraSpec("front", W, H), CameraSpec("wrist", W, H)],
            vcodec=args.vcodec,
        )
        recorder = RolloutRecorder(sink, joint_names=robot.joint_names)
        runner = _runner(recorder, realtime)
        runner.activate()
        on: list[RunResult] = []
        rss: list[float] = []
        try:
            for episode in range(args.episodes):
                runner.episode_start(f"episode {episode}")
                on.append(runner.run(duration_s=args.seconds / args.episodes))
                runner.episode_end(success=True)
                while len(recorder.episodes) < episode + 1 and recorder.errors == 0:
                    time.sleep(0.01)  # the next episode starts once this one is committed
                rss.append(_rss_mb())
        finally:
            runner.deactivate()
        close_s = [e.close_s for e in recorder.episodes]

    print(_line("off", off))
    print(_line("on", on))
    added = float(np.median([r.tick_ms_p50 for r in on])) - off[0].tick_ms_p50
    print(f"tick time added by recording (p50): {added * 1e3:+.1f} µs per tick (target <= 20 µs)")
    print(
        f"episode close s: max {max(close_s):.3f}  median {float(np.median(close_s)):.3f}  "
        f"(target < 1 s; {len(close_s)} episodes, {sum(e.frames for e in recorder.episodes)} frames)"
    )
    print(f"RSS MB after each episode: {' '.join(f'{m:.0f}' for m in rss)}")
    print(
        f"repeated video frames {recorder.repeated_frames}, dropped ticks {recorder.dropped_ticks}, "
        f"recorder errors {recorder.errors}"
    )
    print(machine_line())


if __name__ == "__main__":
    main()
