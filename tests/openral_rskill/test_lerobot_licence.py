"""The licence of a policy class from a LeRobot plugin package: read from its distribution, passed through the gate."""

from __future__ import annotations

import pytest
from tests.conftest import InstalledPackages

from openral_core import ROSLicenseError
from openral_rskill.lerobot.licence import check_policy_license, declared_license


def test_a_plugin_package_declares_its_licence_or_is_noassertion(installed_package: InstalledPackages) -> None:
    installed_package("lerobot_policy_licensed_one", "", importable=True, license_id="MIT")
    installed_package("lerobot_policy_unlicensed_one", "", importable=True)
    assert declared_license("lerobot_policy_licensed_one.modeling") == ("lerobot_policy_licensed_one", "MIT")
    assert declared_license("lerobot_policy_unlicensed_one") == ("lerobot_policy_unlicensed_one", "NOASSERTION")
    assert declared_license("lerobot.policies.act.modeling_act") is None  # LeRobot's own: under its licence


def test_an_unlicensed_plugin_policy_runs_only_when_noassertion_is_accepted(
    installed_package: InstalledPackages,
) -> None:
    installed_package("lerobot_policy_unlicensed_two", "", importable=True)
    with pytest.raises(ROSLicenseError) as caught:
        check_policy_license("lerobot_policy_unlicensed_two.modeling", "unlicensed_two", None)
    text = str(caught.value)
    assert "licence 'NOASSERTION' of the package lerobot_policy_unlicensed_two" in text
    assert "which provides policy type 'unlicensed_two'" in text
    assert "declares no licence" in text
    assert caught.value.field == "params.accept_licenses"
    check_policy_license("lerobot_policy_unlicensed_two.modeling", "unlicensed_two", ["Apache-2.0", "NOASSERTION"])


def test_a_plugin_licence_passes_the_open_list_and_an_explicit_list_replaces_it(
    installed_package: InstalledPackages,
) -> None:
    installed_package("lerobot_policy_mit_three", "", importable=True, license_id="MIT")
    check_policy_license("lerobot_policy_mit_three", "mit_three", None)  # open by default
    with pytest.raises(ROSLicenseError, match="licence 'MIT' of the package lerobot_policy_mit_three"):
        check_policy_license("lerobot_policy_mit_three", "mit_three", ["Apache-2.0"])
