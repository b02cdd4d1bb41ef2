"""``MujocoTwinHAL``: the robot's MuJoCo model, stepped in real time on a background thread.

The twin is physics, not a dictionary: ``send_action`` only moves the position actuators'
setpoints (``data.ctrl``), and ``read_state`` reports the joints where the simulated servos
have actually carried them, with gravity sag, friction and finite speed. A daemon thread
keeps simulated time level with wall time (times ``realtime_factor``): it wakes every
``sync_period_s``, steps as many physics steps as the clock has advanced, and sleeps.
``mj_step`` releases the GIL, and the thread does a few lines of Python per wake-up, so it
costs the tick thread little.

A camera reader renders the same scene through :meth:`MujocoTwinHAL.locked_scene`: it copies
the scene under the physics lock (fast) and renders outside it, so a render never stalls physics.

The gripper is commanded in the model's radians, like every other joint (see the manifest).
"""

from __future__ import annotations

import functools
import math
import threading
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from openral_core.actions import Action
from openral_core.config import validate_model
from openral_core.errors import ROSConfigError, ROSDependencyMissing, ROSHardwareError
from openral_core.robot import RobotManifest
from openral_core.world import JointState
from openral_hal.joints import JointIndex, initial_positions
from openral_hal.model_files import resolve_model_file

try:
    import mujoco
except ImportError as exc:
    raise ROSDependencyMissing("mujoco", extra="twin", needed_for="the MuJoCo twin HAL") from exc

_JOIN_TIMEOUT_S = 5.0


class MujocoTwinParams(BaseModel):
    """Parameters of the ``mujoco_twin`` HAL.

    Attributes:
        realtime_factor: Simulated seconds per wall-clock second (1 = real time).
        initial_positions: Start position per joint name (model units); unnamed joints start at 0
            clipped into their limits.
        settle_s: Simulated seconds stepped at construction, holding the start pose, so the arm
            has already sagged under gravity when the first ``read_state`` comes.
        sync_period_s: How often the physics thread wakes to catch simulated time up with the clock.
        max_lag_s: If physics falls further behind the clock than this (an overloaded machine), the
            backlog is skipped instead of stepped in a burst; the skipped time is counted in ``skipped_s``.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    realtime_factor: float = Field(default=1.0, gt=0, le=100)
    initial_positions: dict[str, float] = Field(default_factory=dict)
    settle_s: float = Field(default=0.5, ge=0, le=10)
    sync_period_s: float = Field(default=0.002, gt=0, le=0.05)
    max_lag_s: float = Field(default=0.1, gt=0, le=5)


class MujocoTwinHAL:
    """A simulated robot that runs in real time and is driven like the real one.

    Args:
        manifest: The robot; its ``mujoco`` entry names the model file inside an installed package.
        params: Validated as :class:`MujocoTwinParams`.

    Raises:
        ROSConfigError: A wrong parameter, a manifest without a MuJoCo model, a model file that is
            missing or does not load, or a manifest joint the model lacks (or has no actuator for).
        ROSDependencyMissing: The package that ships the model is not installed.
    """

    adapter = "mujoco_twin"

    def __init__(self, manifest: RobotManifest, params: Mapping[str, Any] | None = None) -> None:
        self.params = validate_model(
            MujocoTwinParams, dict(params or {}), source="the mujoco_twin HAL", field_prefix="hal.params"
        )
        self.manifest = manifest
        self.robot_id = manifest.robot_id
        self.joint_names = manifest.joint_names
        self._index = JointIndex(self.robot_id, self.joint_names)
        if manifest.mujoco is None:
            raise ROSConfigError(
                f"robot '{self.robot_id}' has no MuJoCo model, so the mujoco_twin HAL cannot simulate it",
                field="hal.adapter",
                hint="pick a robot whose manifest has a 'mujoco' entry, or another adapter",
            )
        self.model_path = resolve_model_file(manifest.mujoco, self.robot_id, needed_for="the MuJoCo twin")
        self.model = _load_model(self.model_path)
        self._data = mujoco.MjData(self.model)
        self._bind_joints()

        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._fault: BaseException | None = None
        self._skipped_s = 0.0
        self._reset(initial_positions(manifest, self.params.initial_positions))

    def _bind_joints(self) -> None:
        """Find each manifest joint's qpos/qvel address and the position actuator that drives it."""
        model = self.model
        one_dof = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
        by_joint = int(mujoco.mjtTrn.mjTRN_JOINT)
        servo_bias = int(mujoco.mjtBias.mjBIAS_AFFINE)
        qpos, qvel, actuators, lower, upper = [], [], [], [], []
        for spec in self.manifest.joints:
            jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, spec.name)
            if jid < 0 or int(model.jnt_type[jid]) not in one_dof:
                raise ROSConfigError(
                    f"{self.model_path} has no hinge or slide joint named '{spec.name}'",
                    field="joints",
                    hint=f"make robot '{self.robot_id}' name the model's joints",
                )
            driving = [
                a
                for a in range(model.nu)
                if int(model.actuator_trntype[a]) == by_joint and int(model.actuator_trnid[a, 0]) == jid
            ]
            if not driving:
                raise ROSConfigError(f"{self.model_path} has no actuator on joint '{spec.name}'", field="mujoco.path")
            act = driving[0]
            if int(model.actuator_biastype[act]) != servo_bias or not model.actuator_biasprm[act, 1] < 0:
                raise ROSConfigError(
                    f"the actuator on joint '{spec.name}' in {self.model_path} is not a position servo",
                    field="mujoco.path",
                    hint="the twin commands joint positions: use a <position> actuator",
                )
            lo, hi = spec.lower, spec.upper
            if model.actuator_ctrllimited[act]:
                lo, hi = (
                    max(lo, float(model.actuator_ctrlrange[act, 0])),
                    min(hi, float(model.actuator_ctrlrange[act, 1])),
                )
            qpos.append(int(model.jnt_qposadr[jid]))
            qvel.append(int(model.jnt_dofadr[jid]))
            actuators.append(act)
            lower.append(lo)
            upper.append(hi)
        self._qpos_idx = np.array(qpos, dtype=np.intp)
        self._qvel_idx = np.array(qvel, dtype=np.intp)
        self._act_idx = np.array(actuators, dtype=np.intp)
        self._ctrl_lower = np.array(lower)
        self._ctrl_upper = np.array(upper)

    def _reset(self, positions: list[float]) -> None:
        """Put the arm at ``positions``, hold them, and let it settle for ``settle_s`` of simulated time."""
        model, data = self.model, self._data
        mujoco.mj_resetData(model, data)
        start = np.clip(np.array(positions), self._ctrl_lower, self._ctrl_upper)
        data.qpos[self._qpos_idx] = start
        data.ctrl[self._act_idx] = start
        mujoco.mj_forward(model, data)
        steps = round(self.params.settle_s / model.opt.timestep)
        if steps:
            mujoco.mj_step(model, data, nstep=steps)

    # -- HAL -------------------------------------------------------------------------------

    @property
    def is_connected(self) -> bool:
        """``True`` while the physics thread runs (between ``connect()`` and ``disconnect()``, unless it faulted)."""
        thread = self._thread
        return thread is not None and thread.is_alive()

    def connect(self) -> None:
        """Start the physics thread. Simulation resumes from where the last ``disconnect()`` left it."""
        if self.is_connected:
            return
        self._stop.clear()
        self._fault = None
        self._thread = threading.Thread(target=self._physics_loop, name=f"openral-twin-{self.robot_id}", daemon=True)
        self._thread.start()

    def disconnect(self) -> None:
        """Stop and join the physics thread. Idempotent.

        Raises:
            ROSHardwareError: The thread did not stop within a few seconds.
        """
        thread = self._thread
        if thread is None:
            return
        self._stop.set()
        thread.join(_JOIN_TIMEOUT_S)
        if thread.is_alive():
            raise ROSHardwareError(f"the physics thread of the '{self.robot_id}' twin did not stop")
        self._thread = None

    def read_state(self) -> JointState:
        """Measured joint positions (qpos), velocities (qvel) and actuator efforts (N·m), stamped now.

        Raises:
            ROSHardwareError: Not connected, or the physics thread stopped on an error.
        """
        self._require_running()
        with self._lock:
            positions = self._data.qpos[self._qpos_idx].tolist()
            velocities = self._data.qvel[self._qvel_idx].tolist()
            efforts = self._data.actuator_force[self._act_idx].tolist()
        return JointState(
            names=list(self.joint_names),
            positions=positions,
            velocities=velocities,
            efforts=efforts,
            stamp_ns=time.monotonic_ns(),
        )

    def send_action(self, action: Action) -> None:
        """Set the named joints' actuator setpoints to ``action.first``, clipped to the command range.

        Raises:
            ROSConfigError: Unknown joint name or unsupported control mode.
            ROSSafetyViolation: A non-finite value.
            ROSHardwareError: Not connected, or the physics thread stopped on an error.
        """
        indices, values = self._index.targets(action, adapter=self.adapter)
        self._require_running()
        idx = list(indices)
        targets = np.clip(values, self._ctrl_lower[idx], self._ctrl_upper[idx])
        actuators = self._act_idx[idx]
        with self._lock:
            self._data.ctrl[actuators] = targets

    def estop(self) -> None:
        """Set every setpoint to the joint's measured position, so the arm stops where it is.

        Works whether or not the physics thread runs. The arm brakes with the servos' own
        dynamics: on the SO-101 at full speed (~5 rad/s) it overshoots the hold point by about
        0.15 rad and is still within 0.6 s.
        """
        with self._lock:
            held = np.clip(self._data.qpos[self._qpos_idx], self._ctrl_lower, self._ctrl_upper)
            self._data.ctrl[self._act_idx] = held

    # -- what a camera reader needs -----------------------------------------------------------

    @property
    def sim_time_s(self) -> float:
        """Simulated time in seconds since the model was loaded (settling included)."""
        with self._lock:
            return float(self._data.time)

    @property
    def skipped_s(self) -> float:
        """Simulated time dropped because physics fell more than ``max_lag_s`` behind the clock."""
        return self._skipped_s

    @contextmanager
    def locked_scene(self) -> Iterator[tuple[Any, Any]]:
        """Yield ``(model, data)`` with physics paused; keep the block short (copy, then work outside).

        A renderer calls ``mujoco.Renderer.update_scene`` inside the block and ``render`` after it.
        The model is shared by every twin built from the same file: treat it as read-only.
        """
        with self._lock:
            yield self.model, self._data

    # -- internals ---------------------------------------------------------------------------

    def _require_running(self) -> None:
        if self.is_connected:
            return
        if self._fault is not None:
            raise ROSHardwareError(
                f"the '{self.robot_id}' twin stopped: {self._fault}; disconnect and connect to resume"
            ) from self._fault
        raise ROSHardwareError(f"the '{self.robot_id}' twin is not connected; call connect() first")

    def _physics_loop(self) -> None:
        """Step physics so that simulated time tracks ``realtime_factor`` × wall time."""
        model, data = self.model, self._data
        dt = float(model.opt.timestep)
        rate = self.params.realtime_factor
        period = self.params.sync_period_s
        max_lag = self.params.max_lag_s
        bad_qacc = int(mujoco.mjtWarning.mjWARN_BADQACC)
        diverged = int(data.warning[bad_qacc].number)
        wall0 = time.monotonic()
        sim0 = float(data.time)
        try:
            while not self._stop.wait(period):
                # Only this thread writes data.time, so reading it unlocked here is safe.
                lag = sim0 + (time.monotonic() - wall0) * rate - float(data.time)
                if lag > max_lag:
                    sim0 -= lag
                    self._skipped_s += lag
                    continue
                steps = math.floor(lag / dt + 1e-9)
                if steps <= 0:
                    continue
                with self._lock:
                    mujoco.mj_step(model, data, nstep=steps)
                    if data.warning[bad_qacc].number != diverged:
                        raise ROSHardwareError(
                            f"physics of {self.model_path.name} diverged at t={data.time:.3f} s "
                            "(non-finite accelerations); the arm was reset by MuJoCo"
                        )
        except Exception as exc:
            self._fault = exc


@functools.cache
def _load_model(path: Path) -> Any:
    """Compile the MJCF at ``path``, naming the file in the error when MuJoCo rejects it.

    Compiling the SO-101 scene takes about a second (mesh processing), so each file is compiled
    once per process. Sharing is safe: the twin never writes to the model, only to its own ``MjData``.
    """
    try:
        return mujoco.MjModel.from_xml_path(str(path))
    except (ValueError, mujoco.FatalError) as exc:
        raise ROSConfigError(f"MuJoCo cannot load {path}: {exc}", field="mujoco.path") from exc
