"""Skills: the lifecycle base every skill implements, rSkill manifests with licence gating, built-in skills.

Built-in skills (``hello``, ``noop``) are found through the ``openral.skills`` entry-point group and
imported only when a deployment selects them.
"""

from openral_rskill.base import RSkillBase, RSkillPlugin, rSkillBase, validate_params
from openral_rskill.manifest import OPEN_LICENSES, RSkillManifest, builtin_manifest, rSkill

__all__ = [
    "OPEN_LICENSES",
    "RSkillBase",
    "RSkillManifest",
    "RSkillPlugin",
    "builtin_manifest",
    "rSkill",
    "rSkillBase",
    "validate_params",
]
