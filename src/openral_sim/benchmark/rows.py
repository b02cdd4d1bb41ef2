"""A suite's rows: each run with its scene, checked before any episode, and what the report says of each."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple, Protocol

from openral_core import BenchmarkRun, BenchmarkSuite, EpisodeResult, SimEnvironment
from openral_core.config import load_model_yaml
from openral_core.config_files import resolve_user_path
from openral_sim.build import EpisodeBatch, SkillFields, check_evaluation
from openral_sim.env import EnvSpec
from openral_sim.evaluation import summarize, throughput

STEP_LIMIT_KEY = "step_limit"
"""The ``env_kwargs`` key an environment's episode-length convention is named by, carried into the row."""


class Hasher(Protocol):
    """What takes the bytes of the files a suite is read from (``hashlib.sha256()``)."""

    def update(self, data: bytes, /) -> None: ...


class SuiteRow(NamedTuple):
    """One row of a suite: the run as written and its scene with the run's overrides applied."""

    run: BenchmarkRun
    scene: SimEnvironment

    @property
    def label(self) -> str:
        """The row's name in the report: its ``label``, or ``scene/skill``."""
        return self.run.label or f"{self.scene.name}/{self.run.skill}"

    @property
    def seeds(self) -> list[int]:
        """The seeds of the row's first and last episode."""
        return [self.scene.seed, self.scene.seed + self.scene.n_episodes - 1]

    def head(self) -> dict[str, Any]:
        """What a row of the report says about itself, whatever its outcome.

        Its episode length: ``max_steps``, and the convention an environment ends episodes by when
        the scene names one (``env_kwargs.step_limit``: LIBERO's ``lerobot`` or ``openpi``).
        """
        head = {
            "label": self.label,
            "scene": self.scene.name,
            "env": self.scene.env,
            "env_id": self.scene.env_id,
            "skill": self.run.skill,
            "skill_params": self.run.skill_params,
            "seeds": self.seeds,
            "timing": self.scene.timing,
            "max_steps": self.scene.max_steps,
        }
        step_limit = self.scene.env_kwargs.get(STEP_LIMIT_KEY)
        if step_limit is not None:
            head[STEP_LIMIT_KEY] = step_limit
        return head


def with_overrides(scene: SimEnvironment, n_episodes: int | None, seed: int | None) -> SimEnvironment:
    """``scene`` with the episode count and the first seed given (``None`` keeps the scene's)."""
    update: dict[str, Any] = {}
    if n_episodes is not None:
        update["n_episodes"] = n_episodes
    if seed is not None:
        update["seed"] = seed
    return scene.model_copy(update=update) if update else scene


def in_real_time(rows: Sequence[SuiteRow]) -> list[SuiteRow]:
    """Every row with ``virtual_latency: measured``: paced by the wall clock, the policy on its worker."""
    return [row._replace(scene=row.scene.model_copy(update={"virtual_latency": "measured"})) for row in rows]


def load_rows(suite: BenchmarkSuite, config_path: Path, hasher: Hasher, *, render_all: bool) -> list[SuiteRow]:
    """Every row with its scene, read from the scene files (nothing is built); the files go into ``hasher``.

    A row renders its scene's cameras only when it asks to (``render_cameras``) or ``render_all``.

    Raises:
        ROSConfigError: Naming the row's field (``runs[0].scene``).
    """
    rows = []
    for index, run in enumerate(suite.runs):
        field = f"runs[{index}].scene"
        scene_path = resolve_user_path(run.scene, config_path.parent, field=field)
        scene = with_overrides(load_model_yaml(SimEnvironment, scene_path, field=field), run.n_episodes, run.seed)
        if not run.render_cameras and not render_all:
            scene = scene.model_copy(update={"cameras": []})
        hasher.update(scene_path.read_bytes())
        rows.append(SuiteRow(run, scene))
    return rows


def check_rows(rows: Sequence[SuiteRow], *, on_ray: bool) -> None:
    """Every row's environment and skill built once (and let go) before any episode runs.

    Rows of one scene (whatever their names, episode counts and seeds) build its environment once.
    On Ray the simulators may live only on the cluster: without them here, the names are checked.

    Raises:
        ROSConfigError: Naming the row's field (``runs[1].skill``).
    """
    specs: dict[str, EnvSpec | None] = {}
    for index, (run, scene) in enumerate(rows):
        key = scene.model_dump_json(exclude={"name", "n_episodes", "seed"})
        specs[key] = check_evaluation(
            scene,
            run.skill,
            run.skill_params,
            fields=SkillFields.of_row(index),
            spec=specs.get(key),
            simulator_elsewhere=on_ray,
        )


def failed_row(row: SuiteRow, exc: BaseException, episodes: Sequence[EpisodeResult]) -> dict[str, Any]:
    """A row that failed while running: its error and the episodes it ran, and no success rate."""
    message = str(exc) or "interrupted"
    return {
        **row.head(),
        "status": "failed",
        "error": f"{type(exc).__name__}: {message}",
        "episodes": [e.model_dump(mode="json") for e in episodes],
    }


def completed_row(
    row: SuiteRow,
    batch: EpisodeBatch,
    *,
    wall_s: float,
    processes: int | None,
    one_process_per_s: float | None,
    served: dict[str, int] | None,
) -> dict[str, Any]:
    """A row whose episodes all ran: success with its interval, latency, throughput and the episodes.

    Args:
        wall_s: The row's time from its first unit scheduled to its last episode back.
        processes: The processes that shared its episodes (``None`` on Ray).
        one_process_per_s: The baseline's episodes per second for this row, for speed-up and efficiency.
        served: What the row's policy server served, when it had one.
    """
    return {
        **row.head(),
        "status": "completed",
        **summarize(batch.episodes, batch),
        **throughput(len(batch.episodes), wall_s, processes, one_process_per_s),
        "env_builds": sum(batch.env_builds.values()),
        **({"served": served} if served is not None else {}),
        "episodes": [e.model_dump(mode="json") for e in batch.episodes],
    }
