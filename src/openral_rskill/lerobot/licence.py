"""The licence of a LeRobot policy class from a plugin package, passed through the one licence gate.

LeRobot's own policies are Apache-2.0, as LeRobot is. A ``lerobot_policy_*`` plugin brings its own
code (and its own terms), read from the metadata of the distribution that installed the class's
module: ``License-Expression``, else a ``License`` field that is an SPDX id. A package that
declares neither is ``NOASSERTION``: like any model without a licence, it runs only when the
deployment lists that in ``params.accept_licenses``.
"""

from __future__ import annotations

import importlib.metadata
import re
from collections.abc import Collection
from typing import Final

from openral_rskill.manifest import NO_LICENSE, check_license

LEROBOT: Final = "lerobot"
"""LeRobot's own package: its policies come under its licence, which openral already depends on."""

_SPDX_EXPRESSION = re.compile(r"^[A-Za-z0-9][A-Za-z0-9.+-]*( (AND|OR|WITH) [A-Za-z0-9][A-Za-z0-9.+-]*)*$")


def declared_license(module: str) -> tuple[str, str] | None:
    """``(distribution, licence)`` of the package that installed ``module``, or ``None`` for LeRobot's own.

    The licence is an SPDX expression, or :data:`~openral_rskill.manifest.NO_LICENSE` when the
    package declares none (or ships nothing an SPDX id can be read from). A module no installed
    distribution provides (a source tree on ``sys.path``) is named by its top-level package and
    declares nothing.
    """
    top = module.partition(".")[0]
    if top == LEROBOT:
        return None
    names = importlib.metadata.packages_distributions().get(top) or [top]
    try:
        metadata = importlib.metadata.metadata(names[0])
    except importlib.metadata.PackageNotFoundError:
        return names[0], NO_LICENSE
    name = _field(metadata, "Name") or names[0]
    for key in ("License-Expression", "License"):
        value = _field(metadata, key)
        if value and _SPDX_EXPRESSION.match(value):
            return name, value
    return name, NO_LICENSE


def _field(metadata: importlib.metadata.PackageMetadata, key: str) -> str:
    values = metadata.get_all(key) or [""]
    return str(values[0]).strip()


def check_policy_license(module: str, policy_type: str, accept_licenses: Collection[str] | None) -> None:
    """Refuse a policy class from a plugin package whose licence the deployment does not accept.

    Raises:
        ROSLicenseError: Naming the package, its licence (``NOASSERTION`` when it declares none)
            and ``params.accept_licenses``, where it is accepted.
    """
    declared = declared_license(module)
    if declared is None:
        return
    distribution, license_id = declared
    source = f"the package {distribution}, which provides policy type '{policy_type}'"
    check_license(license_id, source, accept_licenses, field="params.accept_licenses")


__all__ = ["LEROBOT", "check_policy_license", "declared_license"]
