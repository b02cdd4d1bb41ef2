"""``MUJOCO_GL`` is checked where every command starts: a value no simulator accepts is a configuration error."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from openral_cli import mujoco_gl
from openral_cli.main import cli
from openral_core import ROSConfigError

ROOT = Path(__file__).resolve().parents[2]
SO101_SCENE = ROOT / "scenes" / "sim" / "so101_pick.yaml"
MOCK_SCENE = ROOT / "scenes" / "sim" / "mock_reach.yaml"
TWIN_CAMERA = ROOT / "deployments" / "so101_twin_camera.yaml"


@pytest.mark.parametrize("value", [None, "egl", "osmesa", "glfw"])
def test_unset_or_a_backend_every_simulator_accepts_passes(value: str | None) -> None:
    mujoco_gl.check_mujoco_gl({} if value is None else {"MUJOCO_GL": value})


@pytest.mark.parametrize("value", ["nonexistent", "", "EGL", "glx"])
def test_any_other_value_is_refused_naming_the_variable_and_what_works_here(
    value: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(mujoco_gl, "available_backends", lambda environ: ["osmesa"])
    with pytest.raises(ROSConfigError) as info:
        mujoco_gl.check_mujoco_gl({"MUJOCO_GL": value})
    assert info.value.field == "MUJOCO_GL"
    assert str(info.value).startswith(f"MUJOCO_GL: {value!r} is not one of")
    assert "one that works on this machine: osmesa)" in str(info.value)


def test_a_machine_with_no_backend_is_told_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(mujoco_gl, "available_backends", lambda environ: [])
    with pytest.raises(ROSConfigError, match="libosmesa6 \\(osmesa\\); none is found on this machine"):
        mujoco_gl.check_mujoco_gl({"MUJOCO_GL": "bad"})


def test_glfw_works_here_only_with_a_display() -> None:
    assert "glfw" not in mujoco_gl.available_backends({})


@pytest.mark.parametrize(
    "args",
    [
        ["sim", "run", "--config", str(MOCK_SCENE), "--skill", "zero", "--n-episodes", "1"],
        ["benchmark", "run", "--config", str(MOCK_SCENE)],
        ["deploy", "--config", str(TWIN_CAMERA), "--max-ticks", "1"],
    ],
    ids=["sim run", "benchmark run", "deploy"],
)
def test_commands_exit_2_with_one_line_before_anything_runs(args: list[str]) -> None:
    result = CliRunner().invoke(cli, args, env={"MUJOCO_GL": "nonexistent"})
    assert result.exit_code == 2, result.output
    assert result.output.startswith("error: MUJOCO_GL: 'nonexistent' is not one of the OpenGL backends")
    assert len(result.output.strip().splitlines()) == 1


def test_a_fresh_process_exits_2_instead_of_mujocos_runtime_error(tmp_path: Path) -> None:
    # In a fresh interpreter MuJoCo reads MUJOCO_GL at import and raised a bare RuntimeError there.
    env = {**os.environ, "MUJOCO_GL": "nonexistent"}
    proc = subprocess.run(
        [sys.executable, "-m", "openral_cli", "sim", "run", "--config", str(SO101_SCENE),
         "--skill", "so101_pick_expert", "--n-episodes", "1", "--no-cameras"],
        capture_output=True, text=True, timeout=120, check=False, env=env, cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith("error: MUJOCO_GL: 'nonexistent'")
    assert "RuntimeError" not in proc.stderr


@pytest.mark.parametrize(("gl", "platform"), [("osmesa", "egl"), ("egl", "osmesa")])
def test_a_mujoco_gl_that_pyopengls_platform_contradicts_is_refused_naming_both(gl: str, platform: str) -> None:
    with pytest.raises(ROSConfigError) as info:
        mujoco_gl.check_mujoco_gl({"MUJOCO_GL": gl, "PYOPENGL_PLATFORM": platform})
    assert info.value.field == "MUJOCO_GL"
    assert f"while PYOPENGL_PLATFORM is {platform!r}" in str(info.value)
    mujoco_gl.check_mujoco_gl({"MUJOCO_GL": gl, "PYOPENGL_PLATFORM": gl})  # agreeing is fine
