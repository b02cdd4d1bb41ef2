"""Evaluation past one process: episodes as independent seeded units, run here, in worker processes, or on Ray.

Episode ``i`` of a scene is reset with seed ``scene.seed + i`` whatever runs it, so splitting the
episodes into units and running them anywhere gives the same outcomes as one process would.

A process that runs units keeps what it built (:class:`~openral_sim.build.SimCache`): its first
unit of a scene builds the environment and the skill, the next ones only reset them. So the units
can be small (one episode each when several processes share the work) and pulled by whichever
process is free, which keeps every process busy until the end, and start-up is paid once per
process rather than once per unit. Ray is imported only when asked for.

Every worker process (and Ray task) starts with one thread per numeric library unless asked
otherwise (:mod:`openral_sim.worker_environment`): processes that each spread their math over
every core fight over the cores, and that, not the scheduling, is what caps scaling.
"""

from __future__ import annotations

import functools
import itertools
import math
import multiprocessing
import multiprocessing.util
import os
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import TracebackType
from typing import Any, TypeVar

import numpy as np
import structlog

from openral_core import EpisodeResult, ObserverConfig, RealTimeStats, ROSDependencyMissing, SimEnvironment
from openral_sim import smoothness
from openral_sim.build import EpisodeBatch, SimCache, SkillFailed
from openral_sim.time_to_success import time_to_success
from openral_sim.worker_environment import spawning_with, worker_environment

_log = structlog.get_logger(__name__)

WILSON_Z_95 = 1.959963984540054

T = TypeVar("T")


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
    """A slice of a scene's episodes for one skill: what one worker runs, as plain data that pickles."""

    scene: SimEnvironment
    skill_id: str
    skill_params: Mapping[str, Any] = field(default_factory=dict)
    first_episode: int = 0
    n_episodes: int = 1
    observers: list[ObserverConfig] = field(default_factory=list)
    """The entries of what watches this unit's episodes (the scene's own, then any added, e.g. a video's);
    each is built where the unit runs."""


def split_episodes(
    scene: SimEnvironment, skill_id: str, skill_params: Mapping[str, Any], n_episodes: int, parts: int
) -> list[EpisodeUnit]:
    """``n_episodes`` cut into at most ``parts`` contiguous units of nearly equal size."""
    parts = max(1, min(parts, n_episodes))
    bounds = np.linspace(0, n_episodes, parts + 1).round().astype(int)
    return [
        EpisodeUnit(scene, skill_id, dict(skill_params), int(lo), int(hi - lo), list(scene.observers))
        for lo, hi in itertools.pairwise(bounds)
        if hi > lo
    ]


def schedule_episodes(
    scene: SimEnvironment, skill_id: str, skill_params: Mapping[str, Any], n_episodes: int, processes: int
) -> list[EpisodeUnit]:
    """The units for ``processes`` processes that each pull the next unit when free, largest first.

    One process gets one unit (it stops at the first fault limit, as a single run does). Several
    share the episodes by factoring: each unit takes a ``1 / (2 * processes)`` share of the
    episodes not yet handed out, at least one. Early units are large, so there are few of them
    (each run of a unit starts with a full garbage collection, tens of ms), and the last ones are
    single episodes, so the processes finish together.
    """
    if processes <= 1:
        return split_episodes(scene, skill_id, skill_params, n_episodes, 1)
    units = []
    first = 0
    while first < n_episodes:
        size = max(1, math.ceil((n_episodes - first) / (2 * processes)))
        units.append(EpisodeUnit(scene, skill_id, dict(skill_params), first, size, list(scene.observers)))
        first += size
    return units


def usable_cpus() -> int:
    """The CPUs this process may run on: its affinity mask where the system has one, else every CPU."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):  # no affinity masks on this system
        return os.cpu_count() or 1


def worker_processes(requested: int, units: int) -> int:
    """How many of ``requested`` worker processes to start for at most ``units`` units of work.

    No more than there are units (a process without one only costs its start-up) nor than
    :func:`usable_cpus` (more would share the CPUs and slow each other down); at least one.
    """
    return max(1, min(requested, units, usable_cpus()))


def run_unit(unit: EpisodeUnit) -> EpisodeBatch:
    """Run one unit (in whatever process or Ray worker calls this) on this process's kept env and skill.

    A skill that kept failing is reported in the batch (``failure``), not raised: the caller
    merges every unit's episodes first, then raises.
    """
    return _run_unit(unit, process_cache())


@functools.cache
def process_cache() -> SimCache:
    """This process's environments and skills: built by its first unit of a scene, closed when it exits."""
    cache = SimCache()
    multiprocessing.util.Finalize(None, cache.close, exitpriority=0)  # at exit, in a worker process too
    return cache


def _run_unit(unit: EpisodeUnit, cache: SimCache) -> EpisodeBatch:
    """Run ``unit``'s episodes with its observers (they replace the scene's own entries for this run)."""
    try:
        return cache.run(
            unit.scene.model_copy(update={"observers": unit.observers}),
            unit.skill_id,
            unit.skill_params,
            first_episode=unit.first_episode,
            n_episodes=unit.n_episodes,
        )
    except SkillFailed as exc:
        return exc.batch


def _call(function: Callable[[], T]) -> T:
    """``function()``: what a Ray task runs for :meth:`Evaluator.in_worker`."""
    return function()


def _warm_worker(unit: EpisodeUnit, ready: Any) -> None:
    """A worker's initializer: build ``unit``'s environment and skill as the process starts, then say so."""
    try:
        _warm(process_cache(), unit)
    finally:
        ready.release()


def _warm(cache: SimCache, unit: EpisodeUnit) -> None:
    """Build ``unit``'s environment and skill in ``cache``; a failure is met again, and reported, by the run."""
    try:
        cache.prepare(unit.scene, unit.skill_id, unit.skill_params)
    except Exception as exc:
        _log.debug("warm-up failed; the first unit builds instead", error=str(exc))


def episode_video_entry(folder: Path, *, episodes: int, prefix: str, option: str = "--save-video") -> ObserverConfig:
    """The ``episode_video`` observer entry ``sim run --save-video`` (or a benchmark's ``--videos``) stands for.

    It films the episodes numbered below ``episodes``, each into ``<prefix>_episode<N>.mp4``.
    """
    params = {"folder": str(folder.expanduser().absolute()), "episodes": episodes, "prefix": prefix}
    return ObserverConfig.shorthand("episode_video", params, option=option)


def with_observers(units: Sequence[EpisodeUnit], *entries: ObserverConfig) -> list[EpisodeUnit]:
    """The units, each also watched by ``entries`` (an ``episode_video`` entry films the episodes it asks for)."""
    return [replace(unit, observers=[*unit.observers, *entries]) for unit in units]


class Evaluator:
    """Runs units here, in worker processes that live as long as the evaluator (every row of a suite), or on Ray.

    Args:
        workers: Processes on this machine (spawned, so no simulator state is shared); 1 runs here.
        ray_address: Run the units as Ray tasks: ``auto`` (a running cluster), ``local`` (start
            one here), or a cluster address (``ray://host:10001``). A Ray already initialised in
            this process is used as it is. A Ray worker process keeps what it built as a local
            worker does.
        threads_per_worker: The threads each numeric library (BLAS, OpenMP, PyTorch, ONNX
            Runtime) may use in each worker process or Ray task; a skill whose parameters name
            a count keeps it. ``None``: one in worker processes and on Ray, and one process
            (``workers=1``) runs the episodes here as it is. A count with ``workers=1`` runs them
            in one worker process, where the count applies. ``0``: no limit anywhere.

    Raises:
        ValueError: ``threads_per_worker`` is negative.
    """

    def __init__(
        self, *, workers: int = 1, ray_address: str | None = None, threads_per_worker: int | None = None
    ) -> None:
        if threads_per_worker is not None and threads_per_worker < 0:
            raise ValueError(f"threads_per_worker must be 0 or more, not {threads_per_worker}")
        self.workers = workers
        self.ray_address = ray_address
        self.threads_per_worker = threads_per_worker
        self._here = SimCache()
        self._pool: ProcessPoolExecutor | None = None
        self._warm_ready: Any = None
        self._warming: list[Future[int]] = []
        self._ray_run: Any = None

    @property
    def processes(self) -> int | None:
        """How many processes share the units: ``workers``, or ``None`` on Ray (the cluster decides)."""
        return None if self.ray_address is not None else self.workers

    @property
    def threads(self) -> int | None:
        """The threads each numeric library may use where the episodes run; ``None``: not limited."""
        if self.threads_per_worker is not None:
            return self.threads_per_worker or None
        return None if self.ray_address is None and self.workers <= 1 else 1

    @property
    def _spawns(self) -> bool:
        """Whether the episodes run in worker processes on this machine (not here, not on Ray)."""
        return self.ray_address is None and (self.workers > 1 or self.threads is not None)

    def schedule(
        self, scene: SimEnvironment, skill_id: str, skill_params: Mapping[str, Any], n_episodes: int
    ) -> list[EpisodeUnit]:
        """A row's units (:func:`schedule_episodes`) for this evaluator's processes; on Ray, the cluster's CPUs."""
        processes = self.processes
        if processes is None:
            ray, _ = self._ray()
            processes = max(1, int(ray.cluster_resources().get("CPU", 1)))
        return schedule_episodes(scene, skill_id, skill_params, n_episodes, processes)

    def warm_up(self, unit: EpisodeUnit) -> None:
        """Build ``unit``'s environment and skill where its episodes will run, before they are asked for.

        Worker processes are started now, each building them as it starts, and this returns at
        once: their start-up (interpreter, imports, model load) overlaps whatever this process
        does next, such as checking a suite's rows; :meth:`wait_warm` waits for the end of it.
        In one process they are built here, now. Best effort: what fails here fails again in
        the run, which reports it. Nothing happens on Ray.
        """
        if self.processes is None:
            return
        if not self._spawns:
            _warm(self._here, unit)
        elif self._pool is None:
            context = multiprocessing.get_context("spawn")
            self._warm_ready = context.Semaphore(0)
            self._pool = ProcessPoolExecutor(
                max_workers=self.workers,
                mp_context=context,
                initializer=_warm_worker,
                initargs=(unit, self._warm_ready),
            )
            # A worker process starts at a submit that finds none idle: one submit each starts them all.
            with spawning_with(worker_environment(self.threads)):
                self._warming = [self._pool.submit(os.getpid) for _ in range(self.workers)]

    def wait_warm(self) -> None:
        """Wait until every worker started by :meth:`warm_up` has built what it was given (or failed to)."""
        ready, self._warm_ready = self._warm_ready, None
        waiting = self.workers if ready is not None else 0
        while waiting:
            if ready.acquire(timeout=0.1):
                waiting -= 1
            elif any(future.done() and future.exception() is not None for future in self._warming):
                return  # a worker died starting: the run reports the broken pool

    def run(self, units: Sequence[EpisodeUnit]) -> EpisodeBatch:
        """Run every unit and merge the results in episode order.

        Raises:
            SkillFailed: The skill kept failing in some unit (every unit's episodes are in its ``batch``).
        """
        if self.ray_address is not None:
            batches = self._run_on_ray(units)
        elif self._spawns:
            with spawning_with(worker_environment(self.threads)):  # a submit may start a worker
                results = self._worker_pool().map(run_unit, units)
            batches = list(results)
        else:
            batches = []
            for unit in units:
                batches.append(_run_unit(unit, self._here))
                if batches[-1].failure is not None:
                    break  # as one process running every episode stops at the fault limit
        merged = merge_batches(batches)
        merged.raise_for_failure()
        return merged

    def in_worker(self, function: Callable[[], T]) -> T:
        """``function()`` where this evaluator's episodes run: a worker process, a Ray task like theirs, or here.

        ``function`` must pickle (a module-level function, or a :func:`functools.partial` of one).
        """
        if self.ray_address is not None:
            ray, _ = self._ray()
            task = ray.remote(_call).options(**self._ray_options())
            return ray.get(task.remote(function))  # type: ignore[no-any-return]
        if self._spawns:
            with spawning_with(worker_environment(self.threads)):
                future = self._worker_pool().submit(function)
            return future.result()
        return function()

    def _worker_pool(self) -> ProcessPoolExecutor:
        """The worker processes (started by :meth:`warm_up`, else now, without a warm-up)."""
        if self._pool is None:
            context = multiprocessing.get_context("spawn")
            self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=context)
        return self._pool

    def _ray_options(self) -> dict[str, Any]:
        """A Ray task's options: its worker process starts with the thread limits in its environment.

        Ray's own default sets ``OMP_NUM_THREADS`` alone (to the task's CPUs), and only as a task
        starts where it is unset: not the variables other libraries read, nor before the worker
        has loaded what it loaded.
        """
        environment = worker_environment(self.threads)
        return {"runtime_env": {"env_vars": environment}} if environment else {}

    def close(self) -> None:
        """Stop the worker processes (each closes what it built) and close what was built here. Idempotent."""
        pool, self._pool = self._pool, None
        try:
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
        finally:
            self._here.close()

    def __enter__(self) -> Evaluator:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, traceback: TracebackType | None
    ) -> None:
        self.close()

    def _run_on_ray(self, units: Sequence[EpisodeUnit]) -> list[EpisodeBatch]:
        ray, remote = self._ray()
        task = remote.options(**self._ray_options())
        return list(ray.get([task.remote(unit) for unit in units]))

    def ray(self) -> Any:
        """The ``ray`` module, initialised at this evaluator's address (for what runs beside the tasks)."""
        return self._ray()[0]

    def _ray(self) -> tuple[Any, Any]:
        """Ray, initialised, and :func:`run_unit` as its remote function."""
        if self._ray_run is None:
            if self.ray_address == "local":
                # Under ``uv run`` Ray would start each local worker in a fresh uv environment built from a
                # packaged copy of the project (a network install, per worker); this machine's workers use
                # this interpreter. A user who wants that can still set the variable.
                os.environ.setdefault("RAY_ENABLE_UV_RUN_RUNTIME_ENV", "0")
            try:
                import ray  # noqa: PLC0415
            except ImportError as exc:
                raise ROSDependencyMissing("ray", extra="ray", needed_for="evaluating on a Ray cluster") from exc
            if not ray.is_initialized():
                address = None if self.ray_address == "local" else self.ray_address
                ray.init(address=address, include_dashboard=False, log_to_driver=False)
            self._ray_run = (ray, ray.remote(run_unit))
        return self._ray_run  # type: ignore[no-any-return]


def run_units(
    units: Sequence[EpisodeUnit],
    *,
    workers: int = 1,
    ray_address: str | None = None,
    threads_per_worker: int | None = None,
) -> EpisodeBatch:
    """Run every unit with a one-off :class:`Evaluator` (its worker processes end with the call).

    Raises:
        SkillFailed: The skill kept failing in some unit (every unit's episodes are in its ``batch``).
    """
    with Evaluator(workers=workers, ray_address=ray_address, threads_per_worker=threads_per_worker) as evaluator:
        return evaluator.run(units)


def merge_batches(batches: Sequence[EpisodeBatch]) -> EpisodeBatch:
    """The batches' episodes in episode order; the failure of the first failed batch (in the given order)."""
    merged = EpisodeBatch(episodes=[])
    for batch in batches:
        merged.episodes.extend(batch.episodes)
        merged.tick_ms.extend(batch.tick_ms)
        merged.inference_ms.extend(batch.inference_ms)
        for process, built in batch.env_builds.items():
            merged.env_builds[process] = merged.env_builds.get(process, 0) + built
        if merged.failure is None:
            merged.failure = batch.failure
    merged.episodes.sort(key=lambda e: e.episode_idx)
    return merged


def throughput(
    n_episodes: int, wall_s: float, processes: int | None, one_process_per_s: float | None = None
) -> dict[str, float | None]:
    """How fast episodes ran, as a report carries it.

    ``episodes_per_s`` is ``n_episodes / wall_s`` and ``episodes_per_s_per_worker`` divides it by
    the processes (``None`` on Ray, where the cluster decides). ``speedup`` and ``efficiency``
    (speed-up ÷ processes) need the episodes per second that one process reached on the same
    episodes, measured, not assumed: without it they are ``None``.
    """
    per_s = n_episodes / wall_s if wall_s > 0 else 0.0
    speedup = per_s / one_process_per_s if one_process_per_s else None
    return {
        "wall_s": wall_s,
        "episodes_per_s": per_s,
        "episodes_per_s_per_worker": per_s / processes if processes else None,
        "speedup": speedup,
        "efficiency": speedup / processes if speedup is not None and processes else None,
    }


def summarize(episodes: Sequence[EpisodeResult], batch: EpisodeBatch | None = None) -> dict[str, Any]:
    """LeRobot's aggregates (``pc_success``, ``avg_sum_reward``, ``avg_max_reward``) and the Wilson 95 % interval.

    ``steps_to_success`` summarises the successful episodes only (LeRobot's view); ``time_to_success``
    counts every episode, failures censored at the limit (:mod:`openral_sim.time_to_success`), in
    steps and, where the episodes know their env's rate, in simulated seconds. ``smoothness`` is
    each metric's mean and p95 over the episodes (:mod:`openral_sim.smoothness`; ``None`` for
    episodes that did not record it).

    With the ``batch``, also the tick and inference times' percentiles and histograms
    (:func:`latency_histogram`), which is all a report keeps of the per-step samples.
    """
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
        "time_to_success": time_to_success([e.steps_to_success for e in episodes], _control_hz(episodes)),
        "smoothness": smoothness.summarize(episodes),
    }
    live = [e.real_time for e in episodes if e.real_time is not None]
    if live:
        summary["real_time"] = real_time_summary(live)
    if batch is not None:
        summary["tick_ms"] = _percentiles(batch.tick_ms)
        summary["inference_ms"] = _percentiles(batch.inference_ms)
    return summary


def _control_hz(episodes: Sequence[EpisodeResult]) -> float | None:
    """The rate the row's episodes share (``None``: not recorded, or not one rate)."""
    rates = {e.control_hz for e in episodes}
    return rates.pop() if len(rates) == 1 else None


def real_time_summary(episodes: Sequence[RealTimeStats]) -> dict[str, Any]:
    """A row's real-time figures, pooled over its episodes' env steps and wall time (see :class:`RealTimeStats`)."""
    steps = sum(e.policy_ticks + e.held_slots for e in episodes)
    wall_s = sum(e.wall_s for e in episodes)
    held = sum(e.held_ticks + e.held_slots for e in episodes)
    stale = sum(e.stale_ticks for e in episodes)
    commands = sum(e.fresh_ticks + e.stale_ticks for e in episodes)
    return {
        "stale_or_held_ratio": (held + stale) / steps if steps else 0.0,
        "held_ratio": held / steps if steps else 0.0,
        "stale_ratio": stale / steps if steps else 0.0,
        "held_slots": sum(e.held_slots for e in episodes),
        "commands_per_s": commands / wall_s if wall_s > 0 else 0.0,
        "steps_per_s": steps / wall_s if wall_s > 0 else 0.0,
    }


def real_time_note(summary: dict[str, Any]) -> str:
    """A summary's real-time figures as a clause for a terminal line; empty when it has none."""
    live = summary.get("real_time")
    if not live:
        return ""
    return (
        f"; real time: {100.0 * live['stale_or_held_ratio']:.1f} % of steps stale or held, "
        f"{live['commands_per_s']:.1f} policy commands/s, {live['steps_per_s']:.1f} steps/s"
    )


LATENCY_BINS = 40
"""Bins of a report's latency histogram: the shape of every step's time in a few hundred bytes per row."""


def _percentiles(values: Sequence[float]) -> dict[str, Any]:
    if not values:
        return {"p50": None, "p99": None, "max": None, "histogram": None}
    data = np.asarray(values, dtype=float)
    return {
        "p50": float(np.percentile(data, 50)),
        "p99": float(np.percentile(data, 99)),
        "max": float(data.max()),
        "histogram": latency_histogram(data),
    }


def latency_histogram(values: Sequence[float] | np.ndarray, bins: int = LATENCY_BINS) -> dict[str, Any] | None:
    """How many of ``values`` (ms) fall in each of ``bins`` bins from their minimum to their maximum.

    Latencies are heavy-tailed (a garbage collection, a slow render), so positive values get
    log-spaced bins (``scale: log``): the body and the tail both stay visible in a fixed, small
    number of bins. A run whose steps all took the same time gets one narrow bin around it.

    Returns:
        ``{"scale": "log" | "linear", "edges_ms": [...bins + 1], "counts": [...bins]}``, or
        ``None`` for no values.
    """
    data = np.asarray(values, dtype=float)
    if data.size == 0:
        return None
    low, high = float(data.min()), float(data.max())
    scale = "log" if low > 0 else "linear"
    if high <= low:
        pad = abs(low) * 0.05 or 1e-3
        edges = np.array([low - pad, high + pad])  # positive still when log: the pad is 5 % of a positive value
    elif scale == "log":
        edges = np.geomspace(low, high, bins + 1)
    else:
        edges = np.linspace(low, high, bins + 1)
    counts, _ = np.histogram(data, bins=edges)
    return {"scale": scale, "edges_ms": [float(e) for e in edges], "counts": [int(c) for c in counts]}
