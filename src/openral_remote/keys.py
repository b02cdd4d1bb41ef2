"""The key expressions a policy server answers on: ``openral/<robot>/policy/<name>/{infer,meta,reset,alive}``."""

from __future__ import annotations

import re
from dataclasses import dataclass

from openral_core import ROSConfigError

_SEGMENT = re.compile(r"^[A-Za-z0-9_.\-]+$")


def segment(value: str, field: str) -> str:
    """``value`` if it can be one segment of a key expression (no wildcard, no slash, not empty).

    Every openral key is built from segments checked here.

    Raises:
        ROSConfigError: Naming ``field``, with the characters allowed.
    """
    if not _SEGMENT.match(value):
        raise ROSConfigError(
            f"{value!r} cannot be part of a key expression",
            field=field,
            hint="use letters, digits, '_', '-' and '.' only",
        )
    return value


@dataclass(frozen=True)
class PolicyKeys:
    """Where one served policy lives.

    Attributes:
        infer: Queryable: an observation in, a chunk out.
        meta: Queryable: what the policy is (:class:`openral_remote.meta.PolicyMeta`).
        reset: Queryable: start a new episode.
        alive: Liveliness token, declared once the policy has warmed up.
    """

    robot: str
    policy: str

    @classmethod
    def of(cls, robot: str, policy: str) -> PolicyKeys:
        """The keys of ``policy`` for ``robot`` (both checked: no wildcards, no slashes)."""
        return cls(segment(robot, "robot"), segment(policy, "policy"))

    @property
    def prefix(self) -> str:
        return f"openral/{self.robot}/policy/{self.policy}"

    @property
    def infer(self) -> str:
        return f"{self.prefix}/infer"

    @property
    def meta(self) -> str:
        return f"{self.prefix}/meta"

    @property
    def reset(self) -> str:
        return f"{self.prefix}/reset"

    @property
    def alive(self) -> str:
        return f"{self.prefix}/alive"
