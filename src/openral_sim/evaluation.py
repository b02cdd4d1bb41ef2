"""Evaluation past one process: episodes as independent seeded units, run here, in worker processes, or on Ray.

Episode ``i`` of a scene is reset with seed ``scene.seed + i`` whatever runs it, so splitting the
episodes into units and running them anywhere gives the same outcomes as one process would.
Ray is imported only when asked for.
"""

from __future__ import annotations

import itertools
import math
import multiprocessing
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from openral_core import EpisodeResult, ROSConfigError, ROSDependencyMissing, SimEnvironment
from openral_observability.observer import TickObserver
from openral_sim.build import EpisodeBatch, SkillFailed, run_episodes
from openral_sim.env import EnvSpec

WILSON_Z_95 = 1.959963984540054


def wilson_interval(successes: int, n: int, z: float = WILSON_Z_95) -> tuple[float, float]:
    """The Wilson score interval of a success rate (95 % by default): honest at 0 % and 100 % and for small n."""
    if n <= 0:
        return (0.0, 1.0)
    p = successes / n
    denominator = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denominator
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denominator
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == n else min(1.0, centre + half)
    return (low, high)


@dataclass(frozen=True)
class EpisodeUnit:
    """A slice of a scene's episodes for one skill: what one worker runs."""

    scene: SimEnvironment
    skill_id: str
    skill_params: Mapping[str, Any] = field(default_factory=dict)
    first_episode: int = 0
    n_episodes: int = 1
    video_dir: str | None = None
    """Film this unit's episodes below ``videos`` into this folder (the scene's first camera)."""
    videos: int = 0


def split_episodes(
    scene: SimEnvironment, skill_id: str, skill_params: Mapping[str, Any], n_episodes: int, parts: int
) -> list[EpisodeUnit]:
    """``n_episodes`` cut into at most ``parts`` contiguous units of nearly equal size."""
    parts = max(1, min(parts, n_episodes))
    bounds = np.linspace(0, n_episodes, parts + 1).round().astype(int)
    return [
        EpisodeUnit(scene, skill_id, dict(skill_params), int(lo), int(hi - lo))
        for lo, hi in itertools.pairwise(bounds)
        if hi > lo
    ]


def run_unit(unit: EpisodeUnit) -> EpisodeBatch:
    """Run one unit start to finish (in whatever process or Ray worker calls this).

    A skill that kept failing is reported in the batch (``failure``), not raised: the caller
    merges every unit's episodes first, then raises.
    """
    observers = []
    if unit.video_dir is not None and unit.first_episode < unit.videos and unit.scene.cameras:
        observers.append(
            video_writer(unit.scene, Path(unit.video_dir), unit.videos, f"{unit.scene.name}_{unit.skill_id}")
        )
    try:
        return run_episodes(
            unit.scene,
            unit.skill_id,
            unit.skill_params,
            first_episode=unit.first_episode,
            n_episodes=unit.n_episodes,
            observers=observers,
        )
    except SkillFailed as exc:
        return exc.batch


def video_writer(scene: SimEnvironment, folder: Path, episodes: int, prefix: str) -> Callable[[EnvSpec], TickObserver]:
    """A factory of the video writer filming ``scene``'s first camera at the env's rate.

    Raises:
        ROSConfigError: The scene renders no camera.
    """
    if not scene.cameras:
        raise ROSConfigError(
            "the scene renders no camera to film", field="cameras", hint="add one under cameras: in the scene"
        )

    def make(spec: EnvSpec) -> TickObserver:
        from openral_sim.video import EpisodeVideoWriter  # noqa: PLC0415

        return EpisodeVideoWriter(
            folder,
            camera=scene.cameras[0].name,
            fps=scene.rate_hz or spec.control_hz,
            max_episodes=episodes,
            prefix=prefix,
        )

    return make


def with_videos(units: Sequence[EpisodeUnit], folder: Path, videos: int) -> list[EpisodeUnit]:
    """The units, told to film the episodes below ``videos`` into ``folder``."""
    return [replace(unit, video_dir=str(folder), videos=videos) for unit in units]


def run_units(units: Sequence[EpisodeUnit], *, workers: int = 1, ray_address: str | None = None) -> EpisodeBatch:
    """Run every unit and merge the results in episode order.

    Args:
        workers: Processes on this machine (spawned, so no simulator state is shared); 1 runs here.
        ray_address: Run the units as Ray tasks: ``auto`` (a running cluster), ``local`` (start
            one here), or a cluster address (``ray://host:10001``). A Ray already initialised in
            this process is used as it is.

    Raises:
        SkillFailed: The skill kept failing in some unit (every unit's episodes are in its ``batch``).
    """
    if ray_address is not None:
        batches = _run_on_ray(units, ray_address)
    elif workers > 1 and len(units) > 1:
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
            batches = list(pool.map(run_unit, units))
    else:
        batches = []
        for unit in units:
            batches.append(run_unit(unit))
            if batches[-1].failure is not None:
                break  # as one process running every episode stops at the fault limit
    merged = merge_batches(batches)
    merged.raise_for_failure()
    return merged


def merge_batches(batches: Sequence[EpisodeBatch]) -> EpisodeBatch:
    """The batches' episodes in episode order; the failure of the first failed batch (in the given order)."""
    merged = EpisodeBatch(episodes=[])
    for batch in batches:
        merged.episodes.extend(batch.episodes)
        merged.tick_ms.extend(batch.tick_ms)
        merged.inference_ms.extend(batch.inference_ms)
        if merged.failure is None:
            merged.failure = batch.failure
    merged.episodes.sort(key=lambda e: e.episode_idx)
    return merged


def _run_on_ray(units: Sequence[EpisodeUnit], address: str) -> list[EpisodeBatch]:
    try:
        import ray  # noqa: PLC0415
    except ImportError as exc:
        raise ROSDependencyMissing("ray", extra="ray", needed_for="evaluating on a Ray cluster") from exc
    if not ray.is_initialized():
        ray.init(address=None if address == "local" else address, include_dashboard=False, log_to_driver=False)
    remote = ray.remote(run_unit)
    return list(ray.get([remote.remote(unit) for unit in units]))


def summarize(episodes: Sequence[EpisodeResult], batch: EpisodeBatch | None = None) -> dict[str, Any]:
    """LeRobot's aggregates (``pc_success``, ``avg_sum_reward``, ``avg_max_reward``) and the Wilson 95 % interval."""
    n = len(episodes)
    successes = sum(e.success for e in episodes)
    low, high = wilson_interval(successes, n)
    to_success = [e.steps_to_success for e in episodes if e.steps_to_success is not None]
    summary: dict[str, Any] = {
        "n_episodes": n,
        "n_success": successes,
        "pc_success": 100.0 * successes / n if n else 0.0,
        "pc_success_ci95": [100.0 * low, 100.0 * high],
        "avg_sum_reward": float(np.mean([e.sum_reward for e in episodes])) if n else 0.0,
        "avg_max_reward": float(np.mean([e.max_reward for e in episodes])) if n else 0.0,
        "steps_to_success": {
            "mean": float(np.mean(to_success)) if to_success else None,
            "p50": float(np.median(to_success)) if to_success else None,
        },
    }
    if batch is not None:
        summary["tick_ms"] = _percentiles(batch.tick_ms)
        summary["inference_ms"] = _percentiles(batch.inference_ms)
    return summary


def _percentiles(values: Sequence[float]) -> dict[str, float | None]:
    if not values:
        return {"p50": None, "p99": None, "max": None}
    data = np.asarray(values)
    return {
        "p50": float(np.percentile(data, 50)),
        "p99": float(np.percentile(data, 99)),
        "max": float(data.max()),
    }
