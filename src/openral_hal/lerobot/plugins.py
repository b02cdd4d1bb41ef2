"""LeRobot's third-party plugins, imported once before any LeRobot device or policy is built.

``lerobot_robot_*``, ``lerobot_camera_*``, ``lerobot_teleoperator_*`` and ``lerobot_policy_*``
distributions register their config classes when imported (``RobotConfig.register_subclass``
and its kin). LeRobot's own scripts import them first; openral does the same, so a robot type or
a checkpoint's policy type from such a package resolves like a built-in one.
"""

from __future__ import annotations

import functools


@functools.cache
def load_lerobot_plugins() -> None:
    """Import every installed LeRobot plugin distribution (once per process); needs the ``lerobot`` extra.

    A plugin that fails to import is logged by LeRobot and left out; the type it would have
    registered is then reported as unknown where it is used.
    """
    from lerobot.utils.import_utils import register_third_party_plugins  # noqa: PLC0415  (the extra)

    register_third_party_plugins()
