"""openral hardware abstraction: the ``HAL`` seam, the shipped robot manifests and the adapters.

Adapters are plugins in the ``openral.hals`` entry-point group (``mujoco_twin``, ``null``) and
are imported only when a deployment selects them, so importing this package loads no MuJoCo.
"""

from openral_hal.manifests import known_robots, load_robot_manifest
from openral_hal.protocol import HAL, connected

__all__ = ["HAL", "connected", "known_robots", "load_robot_manifest"]
