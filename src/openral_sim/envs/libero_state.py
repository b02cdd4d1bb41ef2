"""What a LIBERO task's state is translated into: the robot's 8-d state and the privileged object values.

Read from the simulation itself after each step: object and fixture bodies, region sites, and
each movable object's world bounding box (the corners of its collision geoms' boxes, so a
scripted expert knows how tall and how wide what it picks is). The goal's ``On``/``In``
predicates are exposed by position (``goal<i>_object_pos``, ``goal<i>_target_pos``), so a skill
can act on the goal without reading the problem file.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from typing import Any

import numpy as np

from openral_sim.env import SimObservation

try:
    import mujoco
except ImportError as exc:  # pragma: no cover - the libero adapter imports mujoco first
    from openral_core import ROSDependencyMissing

    raise ROSDependencyMissing("mujoco", extra="libero", needed_for="the LIBERO tasks") from exc

_CORNERS = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))
_PLACING = ("on", "in")


class LiberoState:
    """Observes one LIBERO (robosuite) environment; built once, after the model is loaded."""

    def __init__(self, env: Any) -> None:
        self._env = env
        model = env.sim.model._model
        self._data = env.sim.data._data
        self.objects: tuple[str, ...] = tuple(env.objects_dict)
        self._bodies = {name: int(env.obj_body_id[name]) for name in (*env.objects_dict, *env.fixtures_dict)}
        self._sites = {
            name: site
            for name in env.object_sites_dict
            if (site := mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name)) >= 0
        }
        self._boxes = {name: _local_boxes(model, self._bodies[name]) for name in self.objects}
        self.goals: tuple[tuple[str, str], ...] = tuple(
            (str(p[1]), str(p[2]))
            for p in env.parsed_problem["goal_state"]
            if len(p) == 3 and str(p[0]).lower() in _PLACING and p[1] in self._bodies
        )
        self.environment_state_names: tuple[str, ...] = tuple(
            f"{name}_{axis}" for name in self.objects for axis in ("x", "y", "z", "qx", "qy", "qz", "qw")
        )

    def position(self, name: str) -> np.ndarray:
        """A body's or region site's world position."""
        if name in self._sites:
            return np.array(self._data.site_xpos[self._sites[name]])
        return np.array(self._data.xpos[self._bodies[name]])

    def aabb(self, name: str) -> np.ndarray:
        """A movable object's world bounding box: ``[min x, min y, min z, max x, max y, max z]``."""
        geoms, centres, halves = self._boxes[name]
        rotations = self._data.geom_xmat[geoms].reshape(-1, 3, 3)
        local = centres[:, None, :] + _CORNERS[None, :, :] * halves[:, None, :]
        corners = self._data.geom_xpos[geoms][:, None, :] + np.einsum("gij,gcj->gci", rotations, local)
        flat = corners.reshape(-1, 3)
        return np.concatenate([flat.min(axis=0), flat.max(axis=0)])

    def observe(self, obs: Mapping[str, Any], info: dict[str, Any]) -> SimObservation:
        """The robot's state (LeRobot's LIBERO layout) and the privileged values, from robosuite's observation."""
        eef_pos = np.asarray(obs["robot0_eef_pos"], dtype=np.float64)
        eef_quat = np.asarray(obs["robot0_eef_quat"], dtype=np.float64)
        gripper = np.asarray(obs["robot0_gripper_qpos"], dtype=np.float64)
        state = np.concatenate([eef_pos, _rotation_vector(eef_quat), gripper])
        privileged: dict[str, list[float]] = {
            "eef_pos": eef_pos.tolist(),
            "eef_quat": eef_quat.tolist(),
            "gripper_qpos": gripper.tolist(),
        }
        poses: list[np.ndarray] = []
        for name in self.objects:
            position = self.position(name)
            # MuJoCo's w x y z, written x y z w as robosuite's observations are.
            quat = np.roll(np.array(self._data.xquat[self._bodies[name]]), -1)
            privileged[f"{name}_pos"] = position.tolist()
            privileged[f"{name}_quat"] = quat.tolist()
            privileged[f"{name}_aabb"] = self.aabb(name).tolist()
            poses += [position, quat]
        for name in (*self._bodies, *self._sites):
            privileged.setdefault(f"{name}_pos", self.position(name).tolist())
        for index, (thing, target) in enumerate(self.goals):
            privileged[f"goal{index}_object_pos"] = privileged[f"{thing}_pos"]
            privileged[f"goal{index}_object_aabb"] = privileged[f"{thing}_aabb"]
            privileged[f"goal{index}_target_pos"] = privileged[f"{target}_pos"]
        privileged["environment_state"] = np.concatenate(poses).tolist() if poses else []
        return SimObservation(state=state, privileged=privileged, info=info)


def _local_boxes(model: Any, root: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The collision geoms under body ``root`` (all its geoms if none collide) and their boxes in their own frames."""
    under = [g for g in range(model.ngeom) if _descends(model, int(model.geom_bodyid[g]), root)]
    colliding = [g for g in under if model.geom_contype[g] or model.geom_conaffinity[g]]
    geoms = np.array(colliding or under, dtype=np.int64)
    boxes = np.asarray(model.geom_aabb[geoms], dtype=np.float64)
    return geoms, boxes[:, :3], boxes[:, 3:]


def _descends(model: Any, body: int, root: int) -> bool:
    while body > 0:
        if body == root:
            return True
        body = int(model.body_parentid[body])
    return False


def _rotation_vector(quat_xyzw: np.ndarray) -> np.ndarray:
    """A unit quaternion (x y z w) as axis times angle, as LeRobot's LIBERO processor computes it."""
    w = float(np.clip(quat_xyzw[3], -1.0, 1.0))
    sine = np.sqrt(max(1.0 - w * w, 0.0))
    if sine < 1e-12:
        return np.zeros(3)
    return np.asarray(quat_xyzw[:3] * 2.0 * np.arccos(w) / sine, dtype=np.float64)
