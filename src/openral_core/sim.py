"""Simulation contracts: the scene file (``SimEnvironment``), the privileged state a sim exposes, episode outcomes."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal, Self

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from openral_core.config_files import CONFIG_DIR
from openral_core.environment import Watched
from openral_core.execution import ExecutorConfig, VirtualLatency

TimingMode = Literal["virtual", "measured", "real"]
"""How a scene's inference time reaches its episodes: ``virtual`` (a set number of ticks, reproducible),
``measured`` (paced by the wall clock, machine-dependent) or ``real`` (real latency, free-running)."""

SuccessKey = Literal["is_success", "succeed", "success"]
"""The ``info`` keys simulators report success under (gym-pusht/LIBERO, lerobot-env-so101, MetaWorld)."""


class SimCamera(BaseModel):
    """A camera the environment renders each step, into ``WorldState.image_frames`` under its name."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(min_length=1, description="The camera's name in the environment's model (MJCF camera).")
    width: int = Field(default=128, ge=8, le=4096)
    height: int = Field(default=128, ge=8, le=4096)


class SimEnvironment(Watched):
    """A scene file: which environment, which task, how many episodes, what is rendered, who watches.

    Episodes are independent units: episode ``i`` is reset with seed ``seed + i``, so a result
    depends on the seed alone, not on the process or machine that ran it.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(min_length=1, description="Scene name, used in reports.")
    env: str = Field(min_length=1, description="Environment plugin (entry-point group openral.sim_envs).")
    env_id: str | None = Field(default=None, description="The environment's own task id (a gymnasium id, a task).")
    env_kwargs: dict[str, Any] = Field(default_factory=dict, description="Keyword arguments for the environment.")
    robot: str | None = Field(default=None, description="Robot manifest id the scene simulates, when it has one.")
    task: str = Field(min_length=1, description="The task instruction placed in every world state.")
    success_key: SuccessKey = Field(default="is_success", description="The info key that reports success.")
    end_on_success: bool = Field(default=True, description="End an episode at its first successful step.")
    max_steps: int = Field(ge=1, le=1_000_000, description="Steps after which an episode is cut off.")
    n_episodes: int = Field(default=50, ge=1, le=1_000_000)
    seed: int = Field(default=0, ge=0, description="Seed of episode 0; episode i uses seed + i.")
    cameras: list[SimCamera] = Field(default_factory=list, description="Cameras rendered every step.")
    rate_hz: float | None = Field(
        default=None, gt=0, description="Pace ticks at this rate; by default free-running (as fast as the env steps)."
    )
    latency_budget_ms: float | None = Field(default=None, gt=0, description="Steps longer than this are counted.")
    executor: ExecutorConfig = Field(default_factory=ExecutorConfig, description="How chunking skills are executed.")
    virtual_latency: VirtualLatency | Literal["measured"] | None = Field(
        default_factory=VirtualLatency,
        description="Ticks from a chunk request to its use: inference is simulated, so results reproduce. "
        "measured: real time (the wall clock paces the steps at rate_hz, else the env's control rate; the "
        "policy infers on the executor's worker; a late tick's skipped slots are stepped with the hold), so "
        "outcomes depend on the machine. null: the real latency, free-running unless rate_hz is set.",
    )
    base_dir: str | None = Field(
        default=None,
        description="Folder that relative file paths in env_kwargs are resolved against; "
        "by default the scene file's own folder (the working directory for a scene built in code).",
    )

    @model_validator(mode="after")
    def _base_dir_from_file(self, info: ValidationInfo) -> Self:
        folder = (info.context or {}).get(CONFIG_DIR)
        if self.base_dir is None and isinstance(folder, str):
            return self.model_copy(update={"base_dir": folder})
        return self

    @property
    def timing(self) -> TimingMode:
        """How inference time reaches the episodes: ``virtual``, ``measured`` or ``real`` (see ``virtual_latency``)."""
        if self.virtual_latency is None:
            return "real"
        return "measured" if self.virtual_latency == "measured" else "virtual"

    @property
    def simulated_latency(self) -> VirtualLatency | None:
        """The virtual latency when inference is simulated, ``None`` when it takes its real time."""
        return self.virtual_latency if isinstance(self.virtual_latency, VirtualLatency) else None

    def resolve_path(self, path: str) -> Path:
        """``path`` (an ``env_kwargs`` file) as the scene means it: relative to ``base_dir``."""
        candidate = Path(path).expanduser()
        if candidate.is_absolute() or self.base_dir is None:
            return candidate
        return Path(self.base_dir) / candidate

    @field_validator("cameras")
    @classmethod
    def _unique_cameras(cls, cameras: list[SimCamera]) -> list[SimCamera]:
        names = [c.name for c in cameras]
        duplicate = sorted({n for n in names if names.count(n) > 1})
        if duplicate:
            raise ValueError(f"camera {duplicate[0]!r} is listed twice")
        return cameras

    @classmethod
    def from_yaml(cls, path: Path, *, overrides: Sequence[str] = ()) -> Self:
        """Read and validate a scene file, with ``dotted.key=value`` overrides applied (``sim run --set``).

        Raises:
            ROSConfigError: Unreadable file, a malformed override, or a bad field (named, with the fix).
        """
        from openral_core.config import load_model_yaml  # noqa: PLC0415

        return load_model_yaml(cls, path, field="--config", overrides=overrides)


class PrivilegedState(BaseModel):
    """What a simulator knows and a robot cannot measure (object poses, goals, the full env state).

    Only simulated world states carry it; a skill that reads it runs in simulation only.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    values: dict[str, list[float]] = Field(default_factory=dict)

    def get(self, name: str) -> list[float]:
        """One named quantity.

        Raises:
            KeyError: The environment does not expose it (the message lists what it does expose).
        """
        try:
            return self.values[name]
        except KeyError:
            raise KeyError(f"no privileged value {name!r}; the environment exposes {sorted(self.values)}") from None


class EpisodeTiming(BaseModel):
    """How long an episode's steps took: measured, so never part of a reproducibility comparison."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    step_ms_mean: float = 0.0
    step_ms_max: float = 0.0
    inference_ms_mean: float = 0.0
    budget_violations: int = 0


class EpisodeSmoothness(BaseModel):
    """How smoothly the commands that reached the robot moved in one episode (defined in ``openral_sim.smoothness``).

    Computed from the command sent to the env each step, after the safety envelope, held steps
    included. ``None``: the episode was too short for the metric, or the env has no end effector.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", ser_json_inf_nan="constants")

    commands: int = Field(ge=0, description="Commands sent (one per step).")
    jerk_rms: float | None = Field(default=None, description="RMS third derivative of the commanded motion.")
    seams: int = Field(default=0, ge=0, description="Steps whose row came from another chunk than the step before.")
    seam_jump_max: float | None = Field(default=None, description="Largest change of the command at a seam.")
    seam_jump_p95: float | None = Field(default=None, description="95th percentile of the changes at seams.")
    reversals_per_s: float | None = Field(default=None, description="Direction reversals per simulated second.")
    ee_path_length_m: float | None = Field(default=None, description="Path length of the end effector(s), metres.")
    ee_jerk_rms: float | None = Field(default=None, description="RMS jerk of the end effector's measured path, m/s³.")


class RealTimeStats(BaseModel):
    """How an episode kept up with the wall clock (``virtual_latency: measured``): measured, so never compared.

    Every env step is either a *policy tick* (the controller ran) or a *held slot* (a tick overran
    its slot, and the slot was stepped with the hold action, as a robot holds while its
    controller is late). A policy tick is *fresh* when it sent a row the policy computed for that
    very tick (a chunk's row for its own tick, or a non-chunking skill's action), *held* when it
    sent no fresh row (starved or waiting for the first chunk, the fallback acting, or the action
    withheld), and *stale* when it sent a fresh row computed for another tick: only
    ``indexing: stale_start`` does that (each chunk runs from its first row however late it
    arrives); tick-indexed execution skips the rows of past ticks, so it has no stale ticks.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    policy_ticks: int = Field(ge=0, description="Env steps on which the controller ran.")
    held_slots: int = Field(ge=0, description="Env steps of skipped slots, stepped with the hold action.")
    fresh_ticks: int = Field(ge=0, description="Policy ticks that sent a row computed for that tick.")
    held_ticks: int = Field(ge=0, description="Policy ticks that sent no fresh row (starved, none yet, withheld).")
    stale_ticks: int = Field(ge=0, description="Policy ticks that sent a row computed for another tick.")
    wall_s: float = Field(ge=0, description="Wall time from the first step's start to the end of the last's slot.")
    stale_or_held_ratio: float = Field(ge=0, le=1, description="(stale + held ticks + held slots) / env steps.")
    commands_per_s: float = Field(ge=0, description="Rows of the policy sent (fresh or stale) per wall second.")
    steps_per_s: float = Field(ge=0, description="Env steps per wall second.")

    @classmethod
    def of(
        cls, *, policy_ticks: int, held_slots: int, fresh_ticks: int, held_ticks: int, stale_ticks: int, wall_s: float
    ) -> RealTimeStats:
        """The counts with their ratio and rates."""
        steps = policy_ticks + held_slots
        per_s = 1.0 / wall_s if wall_s > 0 else 0.0
        return cls(
            policy_ticks=policy_ticks,
            held_slots=held_slots,
            fresh_ticks=fresh_ticks,
            held_ticks=held_ticks,
            stale_ticks=stale_ticks,
            wall_s=wall_s,
            stale_or_held_ratio=(stale_ticks + held_ticks + held_slots) / steps if steps else 0.0,
            commands_per_s=(fresh_ticks + stale_ticks) * per_s,
            steps_per_s=steps * per_s,
        )


class EpisodeResult(BaseModel):
    """One simulated episode's outcome, derived from its ticks.

    Everything but :attr:`timing` and :attr:`real_time` depends only on the scene, the skill and
    :attr:`seed`, unless the scene runs in real time (``virtual_latency: measured``).
    """

    model_config = ConfigDict(frozen=True, extra="forbid", ser_json_inf_nan="constants")

    episode_idx: int = Field(ge=0)
    seed: int
    success: bool
    steps: int = Field(ge=0)
    steps_to_success: int | None = None
    sum_reward: float = 0.0
    max_reward: float = 0.0
    ended_by: Literal["success", "terminated", "truncated", "max_steps", "skill_done", "faults", "stopped"] = (
        "max_steps"
    )
    """What ended the episode: the task (``success``, ``terminated``, ``truncated``, ``max_steps``), the
    skill (``skill_done``), the fault limit (``faults``: the skill kept failing), or a stop of the run
    (``stopped``: a signal, an e-stop)."""
    timing: EpisodeTiming = Field(default_factory=EpisodeTiming)
    control_hz: float | None = Field(default=None, gt=0)
    """Env steps per simulated second: a step count over it is simulated time (``None`` in older reports)."""
    smoothness: EpisodeSmoothness | None = None
    """Smoothness of the commands sent (``None`` in older reports)."""

    @property
    def seconds_to_success(self) -> float | None:
        """Simulated seconds to the first successful step (``None``: no success, or no known rate)."""
        if self.steps_to_success is None or self.control_hz is None:
            return None
        return self.steps_to_success / self.control_hz

    real_time: RealTimeStats | None = None
    """How the episode kept up with the wall clock; only under ``virtual_latency: measured``."""

    def outcome(self) -> dict[str, Any]:
        """Every field but the measured ones: what must be identical for identical seeds."""
        return self.model_dump(exclude={"timing", "real_time"})


class BenchmarkRun(BaseModel):
    """One row of a benchmark suite: a scene evaluated with one skill."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    scene: str = Field(min_length=1, description="Scene file, relative to the suite file.")
    skill: str = Field(min_length=1, description="Skill id (entry-point group openral.skills).")
    skill_params: dict[str, Any] = Field(default_factory=dict)
    label: str | None = Field(default=None, description="Name in the report (scene/skill by default).")
    n_episodes: int | None = Field(default=None, ge=1, description="Overrides the scene's episode count.")
    seed: int | None = Field(default=None, ge=0, description="Overrides the scene's seed.")
    min_success: float | None = Field(
        default=None, ge=0, le=100, description="Lowest acceptable pc_success (percent) for this row."
    )
    render_cameras: bool = Field(
        default=False,
        description="Render the scene's cameras every step (a skill that sees pixels needs them; tens of ms a step).",
    )


class BenchmarkSuite(BaseModel):
    """A benchmark suite file: scenes × skills, reported together with confidence intervals."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(min_length=1)
    runs: list[BenchmarkRun] = Field(min_length=1)
    videos: int = Field(default=2, ge=0, description="Episodes filmed per row (the first ones) with --videos DIR.")

    @classmethod
    def from_yaml(cls, path: Path) -> Self:
        """Read and validate a suite file.

        Raises:
            ROSConfigError: Unreadable file or a bad field.
        """
        from openral_core.config import load_model_yaml  # noqa: PLC0415

        return load_model_yaml(cls, path, field="--config")
