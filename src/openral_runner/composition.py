"""The one place a run's skills and observers are built, for a deployment and for a simulated scene alike.

``deploy``, ``record``, ``sim run``, ``benchmark run`` and every evaluation worker (a process of
the pool, a Ray task) build the policy, its fallback and the observers here, from the same
entries, through the same registries.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

from openral_core import ExecutorConfig, ObserverConfig, ObserverContext, RobotManifest, ROSConfigError
from openral_core.errors import renamed_field
from openral_core.plugins import OBSERVERS_GROUP, SKILLS_GROUP, PluginRegistry
from openral_observability.observer import ObserverPlugin, TickObserver
from openral_rskill.base import RSkillBase, RSkillPlugin

SKILL_REGISTRY: PluginRegistry[RSkillPlugin] = PluginRegistry(SKILLS_GROUP, kind="skill", field="vla.id")
"""Skill id → skill class (``Cls.from_config(params, robot=..., rate_hz=...)``)."""

OBSERVER_REGISTRY: PluginRegistry[ObserverPlugin] = PluginRegistry(
    OBSERVERS_GROUP, kind="observer", field="observers[].id"
)
"""Observer id → observer plugin (``Cls.from_config(params, context)``)."""

SKILL_PARAMS_FIELDS = ("vla.params", "params")
"""How a skill names its parameters in its errors (a deployment's ``vla.params``, or its own)."""


def build_skill(
    skill_id: str,
    params: Mapping[str, Any],
    *,
    robot: RobotManifest,
    rate_hz: float,
    field: str = "vla.id",
    params_field: str = "vla.params",
) -> RSkillBase:
    """The skill ``skill_id``, unconfigured, for ``robot``'s action space at ``rate_hz``.

    Args:
        field: What names the skill in errors (``vla.id``, ``--skill``, ``runs[0].skill``).
        params_field: What names its parameters in errors (``vla.params``, ``--skill-params``).

    Raises:
        ROSConfigError: An unknown skill or bad parameters, naming ``field`` or ``params_field``.
    """
    skill_class = SKILL_REGISTRY.resolve(skill_id, field=field)
    try:
        skill = skill_class.from_config(dict(params), robot=robot, rate_hz=rate_hz)
    except ROSConfigError as exc:
        raise renamed_field(exc, SKILL_PARAMS_FIELDS, params_field) from exc
    return skill


def build_fallback_skill(executor: ExecutorConfig, *, robot: RobotManifest, rate_hz: float) -> RSkillBase | None:
    """The skill that acts while a chunking skill is starved, if ``executor`` names one.

    Raises:
        ROSConfigError: An unknown skill or bad parameters, naming ``executor.fallback_skill``.
    """
    spec = executor.fallback_skill
    if spec is None:
        return None
    return build_skill(
        spec.id,
        spec.params,
        robot=robot,
        rate_hz=rate_hz,
        field="executor.fallback_skill.id",
        params_field="executor.fallback_skill.params",
    )


def build_observers(entries: Sequence[ObserverConfig], context: ObserverContext) -> list[TickObserver]:
    """Every entry's observer, built for the loop ``context`` describes; none is started.

    An entry a command-line option stands for is built with that option in its context, so its
    errors name the option. When an entry fails, the observers already built are closed again.

    Raises:
        ROSConfigError: An unknown observer id (``observers[i].id``) or what the observer refuses.
    """
    observers: list[TickObserver] = []
    try:
        for index, entry in enumerate(entries):
            plugin = OBSERVER_REGISTRY.resolve(entry.id, field=f"observers[{index}].id")
            observers.append(plugin.from_config(entry.params, replace(context, option=entry.option)))
    except BaseException:
        close_observers(observers)
        raise
    return observers


def close_observers(observers: Sequence[TickObserver]) -> None:
    """Close every observer, each whatever the others do (an observer failing to close is skipped)."""
    for observer in observers:
        with contextlib.suppress(Exception):
            observer.close()


__all__ = [
    "OBSERVER_REGISTRY",
    "SKILL_PARAMS_FIELDS",
    "SKILL_REGISTRY",
    "build_fallback_skill",
    "build_observers",
    "build_skill",
    "close_observers",
]
