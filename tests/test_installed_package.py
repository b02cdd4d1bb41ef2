"""The ``installed_package`` fixture makes a distribution Python's metadata finds as an installed one."""

from __future__ import annotations

import importlib
import importlib.metadata
import os
import subprocess
import sys

import pytest
from tests.conftest import InstalledPackages

NAME = "openral_made_up_plugin"
SOURCE = "from .values import ANSWER\n"
FILES = {"values.py": "ANSWER = 42\n"}


def test_a_child_process_finds_the_distribution_and_imports_it(installed_package: InstalledPackages) -> None:
    installed_package(NAME, SOURCE, files=FILES)
    probe = (
        "import importlib, importlib.metadata as m\n"
        f"names = [d.metadata['Name'] for d in m.distributions() if d.metadata['Name'] == {NAME!r}]\n"
        f"print(names, m.version({NAME!r}), importlib.import_module({NAME!r}).ANSWER)\n"
    )
    env = {**os.environ, "PYTHONPATH": installed_package.pythonpath()}
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.split() == [f"['{NAME}']", "0.1", "42"]
    assert NAME not in sys.modules  # made for the child only


def test_an_importable_package_is_installed_here_until_the_test_ends(installed_package: InstalledPackages) -> None:
    site = installed_package(NAME, SOURCE, files=FILES, importable=True)
    assert [d.metadata["Name"] for d in importlib.metadata.distributions() if d.metadata["Name"] == NAME] == [NAME]
    assert importlib.import_module(NAME).ANSWER == 42
    files = {str(f) for f in importlib.metadata.files(NAME) or []}
    assert {f"{NAME}/__init__.py", f"{NAME}/values.py", f"{NAME}-0.1.dist-info/METADATA"} <= files
    installed_package.remove()
    assert str(site) not in sys.path
    assert not [module for module in sys.modules if module.split(".")[0] == NAME]
    with pytest.raises(importlib.metadata.PackageNotFoundError):
        importlib.metadata.distribution(NAME)
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module(NAME)
