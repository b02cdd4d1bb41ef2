"""``--console [HOST:]PORT``: the option's checks, the entries it stands for, and real runs' stop buttons."""

from __future__ import annotations

import asyncio
import json
import re
import subprocess
import sys
import urllib.request
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import aiohttp
import click
import pytest
from click.testing import CliRunner

from openral_cli.console import (
    ConsoleAddress,
    ConsoleAddressType,
    attach_console,
    with_console,
)
from openral_cli.main import cli
from openral_console.observer import ConsoleObserver
from openral_core import ObserverContext, RobotEnvironment, SimEnvironment
from openral_runner.composition import build_observers
from openral_runner.thumbnails import ThumbnailPublisher

ROOT = Path(__file__).resolve().parents[2]
HELLO = ROOT / "deployments" / "so101_twin_hello.yaml"
MOCK_SCENE = ROOT / "scenes" / "sim" / "mock_reach.yaml"
URL = re.compile(r"console: (http://\S+)")


@pytest.mark.parametrize(
    ("value", "address"),
    [
        ("8080", ConsoleAddress("127.0.0.1", 8080)),
        ("0", ConsoleAddress("127.0.0.1", 0)),
        ("0.0.0.0:8080", ConsoleAddress("0.0.0.0", 8080)),
        ("localhost:9000", ConsoleAddress("localhost", 9000)),
        ("[::1]:8080", ConsoleAddress("::1", 8080)),
    ],
)
def test_the_option_takes_a_port_or_host_and_port(value: str, address: ConsoleAddress) -> None:
    assert ConsoleAddressType().convert(value, None, None) == address


@pytest.mark.parametrize(
    ("value", "says"),
    [
        ("http", "the port must be a number from 0 to 65535"),
        ("70000", "the port must be a number from 0 to 65535"),
        ("host:", "the port must be a number"),
        (":8080", "has no host"),
        ("::1:8080", "IPv6 host in brackets"),
        ("[nope]:8080", "not an IPv6 address"),
    ],
)
def test_a_bad_value_names_the_option_and_the_fix(value: str, says: str) -> None:
    result = CliRunner().invoke(cli, ["deploy", "--config", str(HELLO), "--console", value])
    assert result.exit_code == 2
    assert "--console" in result.output
    assert says in result.output
    with pytest.raises(click.BadParameter):
        ConsoleAddressType().convert(value, None, None)


def test_the_option_adds_a_console_and_thumbnails_for_its_cameras() -> None:
    env = RobotEnvironment.from_yaml(HELLO)
    assert with_console(env, None) is env
    added = with_console(env, ConsoleAddress("0.0.0.0", 0))
    assert [o.id for o in added.observers][-2:] == ["thumbnails", "console"]
    console = added.observers[-1]
    assert console.params == {"host": "0.0.0.0", "port": 0}
    assert console.option == "--console"


def test_a_scene_gets_the_same_entries_built_into_thumbnails_and_a_console_naming_the_option() -> None:
    scene = SimEnvironment.from_yaml(MOCK_SCENE)
    assert with_console(scene, None) is scene
    added = with_console(scene, ConsoleAddress("127.0.0.1", 0))
    assert [o.id for o in added.observers][-2:] == ["thumbnails", "console"]
    made = build_observers(added.observers, ObserverContext(robot_id="mock", rate_hz=30.0))
    try:
        assert isinstance(made[-2], ThumbnailPublisher)
        assert isinstance(made[-1], ConsoleObserver)
        assert made[-1]._option == "--console"
    finally:
        for observer in made:
            observer.close()


def test_attach_console_gives_every_console_the_status_and_buttons() -> None:
    console = ConsoleObserver()
    runner: Any = SimpleNamespace(observers=[object(), console])
    calls: list[str] = []
    attach_console(runner, stop=lambda: calls.append("stop"), next=lambda: calls.append("next"))
    assert console.feed.controls.names() == ["stop", "next"]
    assert console.feed.status is not None
    attach_console(SimpleNamespace(observers=[]), stop=lambda: None)  # no console: nothing to do


def test_the_cli_loads_no_web_server_until_asked() -> None:
    code = "import sys, openral_cli.main; print('aiohttp' in sys.modules, 'openral_console.server' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert proc.stdout.split() == ["False", "False"]


def test_validate_names_the_console_extra_when_aiohttp_is_missing(tmp_path: Path, monkeypatch) -> None:
    config = tmp_path / "console.yaml"
    config.write_text(HELLO.read_text() + "observers:\n  - id: console\n    params: {port: 0}\n")
    assert CliRunner().invoke(cli, ["validate", str(config)]).exit_code == 0
    monkeypatch.setitem(sys.modules, "aiohttp", None)  # import aiohttp now fails, as on an install without it
    result = CliRunner().invoke(cli, ["validate", str(config)])
    assert result.exit_code == 2, result.output
    assert "aiohttp" in result.output
    assert "--extra console" in result.output


def _get(url: str) -> dict[str, Any]:
    with urllib.request.urlopen(url, timeout=10) as response:
        result: dict[str, Any] = json.loads(response.read())
        return result


def _post(url: str) -> int:
    with urllib.request.urlopen(urllib.request.Request(url, method="POST"), timeout=10) as response:
        status: int = response.status
        return status


def _wait_for_state(base: str, ready: Callable[[dict[str, Any]], bool], timeout: float = 60.0) -> dict[str, Any]:
    """The first state the console pushes to a page that satisfies ``ready`` (pushed a few times a second)."""

    async def watch() -> dict[str, Any]:
        async with aiohttp.ClientSession() as session, session.ws_connect(base + "ws") as ws:
            async for message in ws:
                if message.type is aiohttp.WSMsgType.TEXT:
                    state: dict[str, Any] = json.loads(message.data)
                    if state["type"] == "state" and ready(state):
                        return state
        raise AssertionError("the console closed before showing the expected state")

    return asyncio.run(asyncio.wait_for(watch(), timeout))


def test_sim_run_stop_button_ends_the_evaluation_and_its_camera_reaches_the_console(deploy_process, tmp_path) -> None:
    scene = tmp_path / "slow_reach.yaml"
    scene.write_text(MOCK_SCENE.read_text().replace("n_episodes: 20", "n_episodes: 1000") + "rate_hz: 20\n")
    proc = deploy_process(["sim", "run", "--config", str(scene), "--skill", "random", "--console", "0"])
    base = URL.search(proc.wait_for("console: http://")).group(1)  # type: ignore[union-attr]
    state = _wait_for_state(base, lambda s: s["ticks"] > 5 and s["controls"] and s["cameras"])
    assert state["cameras"] == ["top"]
    assert state["status"]["skill_id"] == "random"
    with urllib.request.urlopen(base + "api/camera/top", timeout=10) as response:
        assert response.read()[:2] == b"\xff\xd8"  # a JPEG
    assert _post(base + "api/control/stop") == 200
    code, stdout = proc.finish(timeout=60)
    assert code == 0, proc.stderr
    assert "mock_reach / random:" in stdout
