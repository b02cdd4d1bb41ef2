"""Highlight memory benchmark: an hour of 30 Hz ticks through a recorder in highlight mode, memory sampled as it goes.

A ``RolloutRecorder`` with ``highlight_s`` is fed ``--minutes`` of synthetic 30 Hz ticks (108 000
for an hour), each with ``--cameras`` 640x480 RGB frames (moving gradients plus noise, as in
``recording.py``; every tick's frame is a new buffer, as a camera hands over), as fast as its
worker takes them (the feeder waits while more than a few ticks are queued, so queued raw frames
do not blur the figures). Every simulated ``--sample-min`` minutes it samples the process's
resident memory and what the ring reports (rows and bytes held), and at ``--save-at`` minutes it
saves a highlight (the saves run on the recorder's saving thread while the feeding goes on).
Reported: the samples (flat means nothing accumulates), the JPEG cost per held frame, each save's
time from ``save_highlight()`` to committed (while the feeding goes on, and once more after it
stopped), and the dataset check at the end.

Run:  uv run python benchmarks/highlight_memory.py [--minutes 60] [--highlight-s 30] [--cameras 2]
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path

import numpy as np

from _common import machine_line
from openral_core import FrameEncoding, JointState, SensorFrame, TickResult, WorldState
from openral_dataset.check import check_dataset
from openral_dataset.episode import EpisodeSummary
from openral_dataset.recorder import RolloutRecorder
from openral_dataset.schema import CameraSpec
from openral_dataset.writer import LeRobotDatasetSink
from openral_hal.manifests import load_robot_manifest

W, H, FPS = 640, 480, 30
TICK_NS = 1_000_000_000 // FPS
MAX_QUEUED = 4
"""Ticks the feeder lets wait for the recorder's worker."""


def _frames(seed: int, noise: float) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    x = np.linspace(0, 255, W, dtype=np.float32)[None, :, None]
    y = np.linspace(0, 255, H, dtype=np.float32)[:, None, None]
    base = (x + y) / 2 + rng.normal(0, noise, (H, W, 3)).astype(np.float32)
    return [np.clip(np.roll(base, 8 * i, axis=1), 0, 255).astype(np.uint8) for i in range(64)]


def _rss_mb() -> float:
    """Resident memory now (``/proc``), in MB."""
    with open("/proc/self/statm", encoding="ascii") as statm:
        return int(statm.read().split()[1]) * resource.getpagesize() / 2**20


def _stamp(done_at: dict[int, float], n: int) -> Callable[[object], None]:
    """A future's callback that notes when save ``n`` was committed."""
    return lambda _future: done_at.__setitem__(n, time.perf_counter())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--minutes", type=float, default=60.0, help="simulated run time")
    parser.add_argument("--highlight-s", type=float, default=30.0, help="seconds the ring holds")
    parser.add_argument("--cameras", type=int, default=2, choices=[1, 2])
    parser.add_argument("--vcodec", default="libsvtav1", choices=["libsvtav1", "h264"])
    parser.add_argument("--noise", type=float, default=12.0, help="pixel noise (std dev): higher, bigger JPEGs")
    parser.add_argument("--sample-min", type=float, default=5.0, help="simulated minutes between samples")
    parser.add_argument(
        "--save-at", type=float, nargs="*", default=[10.0, 25.0, 40.0, 55.0], help="simulated minutes of each save"
    )
    args = parser.parse_args()
    print(machine_line())
    robot = load_robot_manifest("so101_follower")
    names = ["front", "wrist"][: args.cameras]
    frames = {name: _frames(seed, args.noise) for seed, name in enumerate(names)}
    ticks = round(args.minutes * 60 * FPS)
    sample_every = round(args.sample_min * 60 * FPS)
    saves_at = {round(m * 60 * FPS) for m in args.save_at if m * 60 * FPS < ticks}
    saves: list[tuple[int, float, Future[EpisodeSummary | None]]] = []
    done_at: dict[int, float] = {}
    samples: list[tuple[float, float, int, int, float, float, int]] = []

    with tempfile.TemporaryDirectory(prefix="openral-bench-") as tmp:
        root = Path(tmp) / "ds"
        sink = LeRobotDatasetSink(
            root,
            fps=FPS,
            robot_type=robot.robot_id,
            joint_names=robot.joint_names,
            cameras=[CameraSpec(name, W, H) for name in names],
            vcodec=args.vcodec,
        )
        recorder = RolloutRecorder(sink, joint_names=robot.joint_names, highlight_s=args.highlight_s)
        ring = recorder.highlight
        assert ring is not None
        recorder.on_episode_start(0, "an hour of work")
        started = last_wall = time.perf_counter()
        last_tick, last_compressed, last_compress_s = 0, 0, 0.0
        zeros = [0.0] * len(robot.joint_names)
        for i in range(ticks + 1):
            if i % sample_every == 0:
                while recorder.handled < i:  # the sample sees every tick so far held
                    time.sleep(0.0005)
                now = time.perf_counter()
                compressed = ring.frames_compressed - last_compressed
                per_frame_ms = (ring.compress_s - last_compress_s) / compressed * 1e3 if compressed else 0.0
                rate = (i - last_tick) / (now - last_wall) if i else 0.0
                saving = sum(not future.done() for _, _, future in saves)
                samples.append((i / FPS / 60, _rss_mb(), ring.rows, ring.nbytes, per_frame_ms, rate, saving))
                last_tick, last_wall, last_compressed, last_compress_s = i, now, ring.frames_compressed, ring.compress_s
            if i == ticks:
                break
            if i in saves_at:
                while recorder.handled < i:  # the save holds every tick so far
                    time.sleep(0.0005)
                future = recorder.save_highlight()
                future.add_done_callback(_stamp(done_at, len(saves)))
                saves.append((i, time.perf_counter(), future))
            stamp = (i + 1) * TICK_NS
            world = WorldState(
                stamp_ns=stamp,
                joint_state=JointState(names=robot.joint_names, positions=zeros, stamp_ns=stamp),
                image_frames={
                    name: SensorFrame(
                        sensor_id=name,
                        stamp_ns=stamp,
                        width=W,
                        height=H,
                        seq=i,
                        encoding=FrameEncoding.RGB8,
                        data=frames[name][i % 64].copy(),  # a camera hands over a new buffer
                    )
                    for name in names
                },
            )
            recorder.on_tick(TickResult(tick_idx=i, start_ns=stamp, step_idx=i), world)
            while recorder.queued > MAX_QUEUED:
                time.sleep(0.0005)
        wall_s = time.perf_counter() - started
        summaries = [future.result() for _, _, future in saves]
        asked = time.perf_counter()  # one more with nothing else running: what a save costs on its own
        alone = recorder.save_highlight().result()
        alone_s = time.perf_counter() - asked
        recorder.on_episode_end(0, success=True)
        recorder.close()
        checked = check_dataset(root, decode_videos=False)

    print(
        f"{ticks} ticks ({args.minutes:g} min at {FPS} Hz), {len(names)} camera(s) {W}x{H}, "
        f"highlight {args.highlight_s:g} s ({ring.capacity_rows} rows), {args.vcodec}, noise {args.noise:g}; "
        f"fed in {wall_s:.0f} s ({ticks / wall_s:.0f} ticks/s)"
    )
    print(
        f"{'sim min':>7} {'RSS MB':>8} {'ring rows':>9} {'ring MB':>8} {'JPEG ms/frame':>13} {'ticks/s':>8} "
        f"{'saves in flight':>15}"
    )
    for minute, rss, rows, nbytes, per_frame_ms, rate, saving in samples:
        print(f"{minute:7.1f} {rss:8.0f} {rows:9d} {nbytes / 2**20:8.1f} {per_frame_ms:13.2f} {rate:8.0f} {saving:15d}")
    held = [s for s in samples if s[2] == ring.capacity_rows]
    if held:
        rss = [s[1] for s in held]
        print(
            f"RSS once the ring was full: min {min(rss):.0f} MB  max {max(rss):.0f} MB  "
            f"(spread {max(rss) - min(rss):.0f} MB)"
        )
    print(f"peak RSS (ru_maxrss) {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    print(
        f"JPEG per held frame: {ring.compress_s / max(1, ring.frames_compressed) * 1e3:.2f} ms mean "
        f"over {ring.frames_compressed} frames"
    )
    for n, (tick, asked, _future) in enumerate(saves):
        summary = summaries[n]
        frames_saved = summary.frames if summary is not None else 0
        print(
            f"save at {tick / FPS / 60:5.1f} min: {frames_saved} rows, "
            f"{done_at.get(n, float('nan')) - asked:.1f} s from save_highlight() to committed"
        )
    print(f"save with the feeding stopped: {alone.frames if alone else 0} rows, {alone_s:.1f} s")
    print(
        f"dataset: {checked.episodes} episodes, {checked.frames} frames, problems {checked.problems or 'none'}; "
        f"recorder errors {recorder.errors}, dropped ticks {recorder.dropped_ticks}"
    )
    print(machine_line())


if __name__ == "__main__":
    main()
