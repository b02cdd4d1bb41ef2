"""Forward kinematics of one site, extracted once from a MuJoCo MJCF file, evaluated in pure Python.

The safety client needs the end-effector position of every commanded joint row, inside the
tick's few-microsecond budget, without importing MuJoCo. :func:`load_site_chain` walks the
MJCF body tree (``<include>`` files, ``<default>`` classes, ``pos``/``quat``, hinge and slide
joints with their ``pos``, ``axis`` and ``ref``) from a base body to a site and compiles it
into a :class:`SiteChain`: one constant point and, per joint, a rotation about (or a slide
along) the local z axis followed by a constant affine map. Each joint's axis is folded into
the neighbouring constant maps, so evaluation is a handful of multiply-adds per joint.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from openral_core.errors import ROSConfigError
from openral_core.robot import RobotManifest
from openral_hal.model_files import resolve_model_file

_Affine = tuple[float, float, float, float, float, float, float, float, float, float, float, float]
_UNSUPPORTED_ORIENTATION = ("axisangle", "euler", "xyaxes", "zaxis")


@dataclass(frozen=True)
class _Joint:
    index: int  # position of the joint in the command row
    slide: bool
    ref: float
    outer: _Affine  # row-major 3x3 rotation then translation, applied after the joint motion


@dataclass(frozen=True)
class SiteChain:
    """Position of one site in a base body's frame as a function of a joint-position row.

    Attributes:
        site: Name of the site in the model.
        base: Name of the body whose frame the positions are expressed in.
        joint_indices: Positions, in the command row, of the joints on the chain (outermost first).
    """

    site: str
    base: str
    joint_indices: tuple[int, ...]
    _point: tuple[float, float, float]
    _joints: tuple[_Joint, ...]  # innermost (closest to the site) first

    def position(self, row: Sequence[float]) -> tuple[float, float, float]:
        """Site position (metres, base frame) for the joint positions ``row`` (manifest order)."""
        x, y, z = self._point
        cos, sin = math.cos, math.sin
        for joint in self._joints:
            q = row[joint.index] - joint.ref
            if joint.slide:
                z += q
            else:
                c, s = cos(q), sin(q)
                x, y = c * x - s * y, s * x + c * y
            r00, r01, r02, r10, r11, r12, r20, r21, r22, tx, ty, tz = joint.outer
            x, y, z = (
                r00 * x + r01 * y + r02 * z + tx,
                r10 * x + r11 * y + r12 * z + ty,
                r20 * x + r21 * y + r22 * z + tz,
            )
        return x, y, z

    def positions(self, rows: np.ndarray) -> np.ndarray:
        """Vectorised :meth:`position` for an ``(n, joints)`` array; returns ``(n, 3)``."""
        rows = np.asarray(rows, dtype=float)
        v = np.broadcast_to(np.asarray(self._point, dtype=float), (rows.shape[0], 3)).copy()
        for joint in self._joints:
            q = rows[:, joint.index] - joint.ref
            if joint.slide:
                v[:, 2] += q
            else:
                c, s = np.cos(q), np.sin(q)
                x = v[:, 0].copy()
                v[:, 0] = c * x - s * v[:, 1]
                v[:, 1] = s * x + c * v[:, 1]
            o = joint.outer
            rot = np.array(o[:9]).reshape(3, 3)
            v = v @ rot.T + np.array(o[9:])
        return v


def load_site_chain(robot: RobotManifest) -> SiteChain:
    """The chain from ``robot.base_frame`` to ``robot.mujoco.ee_site`` in the robot's MJCF model.

    Raises:
        ROSConfigError: The manifest names no model or no ``ee_site``, the file cannot be
            parsed, or the chain uses something this loader does not model (ball or free
            joints, ``<frame>``, orientations other than ``quat``, joints missing from the manifest).
        ROSDependencyMissing: The package holding the model is not installed.
    """
    ref = robot.mujoco
    if ref is None or ref.ee_site is None:
        raise ROSConfigError(
            f"robot '{robot.robot_id}' has no MuJoCo model with an ee_site in its manifest",
            field="mujoco.ee_site",
        )
    path = resolve_model_file(ref, robot.robot_id, needed_for="forward kinematics of the workspace box")
    return chain_from_mjcf(path, site=ref.ee_site, base=robot.base_frame, joint_names=robot.joint_names)


def chain_from_mjcf(path: Path, *, site: str, base: str, joint_names: Sequence[str]) -> SiteChain:
    """Compile the kinematic chain from body ``base`` to ``site``; positions are in ``base``'s frame.

    Raises:
        ROSConfigError: See :func:`load_site_chain`.
    """
    root = _parse(path)
    angle_scale = _angle_scale(root)
    classes = _default_classes(root)
    parents: dict[ET.Element, ET.Element] = {child: parent for parent in root.iter() for child in parent}
    site_el = next((el for el in root.iter("site") if el.get("name") == site), None)
    if site_el is None:
        raise ROSConfigError(f"model {path.name} has no site '{site}'", field="mujoco.ee_site")
    bodies: list[ET.Element] = []
    node = parents.get(site_el)
    while node is not None and node.tag != "worldbody":
        if node.tag != "body":
            raise ROSConfigError(f"model {path.name}: <{node.tag}> on the path to site '{site}' is not supported")
        if node.get("name") == base:
            break
        bodies.append(node)
        node = parents.get(node)
    if node is None or node.get("name") != base:
        raise ROSConfigError(
            f"model {path.name}: body '{base}' is not an ancestor of site '{site}'",
            field="base_frame",
            hint="base_frame must name the model body the workspace box is expressed in",
        )
    bodies.reverse()  # outermost first

    index = {name: i for i, name in enumerate(joint_names)}
    # Transform so far (outer) as a 4x4; joints split it into constant pieces.
    pending = np.eye(4)
    pieces: list[tuple[np.ndarray, int, bool, float]] = []  # (outer map, joint index, slide, ref)
    for body in bodies:
        pending = pending @ _frame(body, path)
        for joint in body:
            if joint.tag == "freejoint":
                raise ROSConfigError(f"model {path.name}: free joint on the path to site '{site}'")
            if joint.tag != "joint":
                continue
            attrs = _joint_attrs(joint, body, parents, classes)
            name = attrs.get("name", "")
            kind = attrs.get("type", "hinge")
            if kind not in ("hinge", "slide"):
                raise ROSConfigError(
                    f"model {path.name}: joint '{name}' is a {kind} joint; only hinge/slide are modelled"
                )
            if name not in index:
                raise ROSConfigError(
                    f"model {path.name}: joint '{name}' on the path to site '{site}' is not in the manifest",
                    field="joints",
                )
            axis = _vector(attrs.get("axis", "0 0 1"))
            axis = axis / np.linalg.norm(axis)
            anchor = _vector(attrs.get("pos", "0 0 0"))
            align = _align_z(axis)  # columns: a frame whose z is the joint axis
            ref_value = float(attrs.get("ref", "0"))
            slide = kind == "slide"
            if not slide:
                ref_value *= angle_scale
            # hinge: T_anchor · R_axis(q) · T_-anchor ;  R_axis = B · Rz · Bᵀ
            pre = np.eye(4)
            pre[:3, :3] = align
            pre[:3, 3] = anchor if not slide else 0.0
            pieces.append((pending @ pre, index[name], slide, ref_value))
            post = np.eye(4)
            post[:3, :3] = align.T
            if not slide:
                post[:3, 3] = -(align.T @ anchor)
            pending = post
    site_frame = pending @ _frame(site_el, path)
    point = [float(v) for v in site_frame[:3, 3]]
    joints = tuple(
        _Joint(index=i, slide=slide, ref=ref_value, outer=_affine(outer))
        for outer, i, slide, ref_value in reversed(pieces)
    )
    return SiteChain(
        site=site,
        base=base,
        joint_indices=tuple(i for _, i, _, _ in pieces),
        _point=(point[0], point[1], point[2]),
        _joints=joints,
    )


def _parse(path: Path) -> ET.Element:
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise ROSConfigError(f"cannot read MuJoCo model {path}: {exc}", field="mujoco.path") from exc
    _expand_includes(root, path.parent)
    return root


def _expand_includes(element: ET.Element, directory: Path) -> None:
    children: list[ET.Element] = []
    for child in element:
        if child.tag == "include":
            children.extend(_parse(directory / child.get("file", "")))
        else:
            _expand_includes(child, directory)
            children.append(child)
    element[:] = children


def _angle_scale(root: ET.Element) -> float:
    angle = next((c.get("angle") for c in root.iter("compiler") if c.get("angle")), "degree")
    return 1.0 if angle == "radian" else math.pi / 180.0


def _default_classes(root: ET.Element) -> dict[str, dict[str, str]]:
    """Joint attributes of every default class, inherited down nested ``<default>`` blocks."""
    classes: dict[str, dict[str, str]] = {}

    def visit(element: ET.Element, inherited: dict[str, str]) -> None:
        attrs = dict(inherited)
        for joint in element.findall("joint"):
            attrs.update(joint.attrib)
        name = element.get("class", "main")
        classes[name] = {**classes.get(name, {}), **attrs}
        for child in element.findall("default"):
            visit(child, attrs)

    for top in root.findall("default"):
        visit(top, classes.get("main", {}))
    return classes


def _joint_attrs(
    joint: ET.Element, body: ET.Element, parents: dict[ET.Element, ET.Element], classes: dict[str, dict[str, str]]
) -> dict[str, str]:
    cls = joint.get("class")
    node: ET.Element | None = body
    while cls is None and node is not None:
        cls = node.get("childclass")
        node = parents.get(node)
    return {**classes.get("main", {}), **classes.get(cls or "main", {}), **joint.attrib}


def _frame(element: ET.Element, path: Path) -> np.ndarray:
    for attr in _UNSUPPORTED_ORIENTATION:
        if element.get(attr) is not None:
            raise ROSConfigError(
                f"model {path.name}: <{element.tag} name='{element.get('name')}'> uses '{attr}'; "
                "the safety kinematics reads only 'quat' orientations"
            )
    frame = np.eye(4)
    frame[:3, 3] = _vector(element.get("pos", "0 0 0"))
    w, x, y, z = _vector(element.get("quat", "1 0 0 0"), size=4)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    frame[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return frame


def _vector(text: str, size: int = 3) -> np.ndarray:
    values = np.array([float(v) for v in text.split()], dtype=float)
    if values.shape != (size,):
        raise ROSConfigError(f"expected {size} numbers in an MJCF attribute, got '{text}'")
    return values


def _align_z(axis: np.ndarray) -> np.ndarray:
    """A rotation whose third column is ``axis`` (identity when ``axis`` is already z)."""
    if np.allclose(axis, (0.0, 0.0, 1.0)):
        return np.eye(3)
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, axis)
    x /= np.linalg.norm(x)
    y = np.cross(axis, x)
    return np.column_stack((x, y, axis))


def _affine(matrix: np.ndarray) -> _Affine:
    r = matrix[:3, :3]
    t = matrix[:3, 3]
    return (
        float(r[0, 0]), float(r[0, 1]), float(r[0, 2]),
        float(r[1, 0]), float(r[1, 1]), float(r[1, 2]),
        float(r[2, 0]), float(r[2, 1]), float(r[2, 2]),
        float(t[0]), float(t[1]), float(t[2]),
    )  # fmt: skip
