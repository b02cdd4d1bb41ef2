"""Two ``openral serve`` of one key: the second is refused however the two are linked; a restart keeps the id.

Real Zenoh sessions on loopback. The servers link directly, through a router, or through a third
peer (both dial it, neither listens); the router and the peer are sessions this test opens.
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from openral_remote.config import ZenohConfig
from openral_remote.session import zenoh_config
from openral_remote.testing import free_endpoint

pytestmark = pytest.mark.timeout(300)

PREFIX = "openral/so101_follower/policy/hello"
REFUSED = (
    f"error: {PREFIX} is already served: another policy server holds its liveliness token {PREFIX}/alive "
    "(stop that server first, or serve this policy under another name (--name))"
)


def _serve(*args: str) -> list[str]:
    return ["serve", "--skill", "hello", "--robot", "so101_follower", *args]


@pytest.fixture
def hub() -> Iterator[Callable[[str], str]]:
    """Open a Zenoh session in ``router`` or ``peer`` mode listening on loopback; returns its endpoint."""
    import zenoh  # noqa: PLC0415 (the 'remote' extra, as the code under test)

    opened: list[Any] = []

    def open_hub(mode: str) -> str:
        endpoint = free_endpoint()
        settings = zenoh_config(ZenohConfig(listen=[endpoint]))
        settings.insert_json5("mode", json.dumps(mode))
        opened.append(zenoh.open(settings))
        return endpoint

    yield open_hub
    for session in opened:
        session.close()


def _zenoh_id(line: str) -> str:
    found = re.search(r"Zenoh id ([0-9a-f]+)$", line.strip())
    assert found, line
    return found.group(1)


def _refused(*args: str) -> None:
    """A second server of the key exits 2 with one line, before printing that it serves."""
    done = subprocess.run(
        [sys.executable, "-m", "openral_cli", *_serve(*args)],
        check=False,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines() == [REFUSED]


def test_a_second_server_dialling_the_first_is_refused_and_a_restart_keeps_the_id(deploy_process) -> None:
    endpoint = free_endpoint()
    first = deploy_process(_serve("--listen", endpoint))
    zid = _zenoh_id(first.wait_for(f"serving {PREFIX}"))
    _refused("--skill-params", '{"chunk_size": 15}', "--connect", endpoint)
    first.signal_group(signal.SIGINT)
    assert first.finish()[0] == 0
    again = deploy_process(_serve("--listen", endpoint))
    assert _zenoh_id(again.wait_for(f"serving {PREFIX}")) == zid  # robots that pinned it take it back
    again.signal_group(signal.SIGINT)
    assert again.finish()[0] == 0


@pytest.mark.parametrize("mode", ["router", "peer"])
def test_a_second_server_behind_the_same_router_or_peer_is_refused(deploy_process, hub, mode: str) -> None:
    through = hub(mode)
    first = deploy_process(_serve("--connect", through))
    first.wait_for(f"serving {PREFIX}")
    _refused("--skill-params", '{"chunk_size": 15}', "--connect", through)
    assert first.proc.poll() is None  # the first one serves on
